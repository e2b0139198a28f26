"""A replay connection's avatars (``posecast replay``): recorded avatars published into a
room as if their players were there.

A replay client (``hello.role`` "replay", which a server with a secret admits with a
player's token) sends a recording's rosters and avatar batches as they were received.
Each recorded avatar becomes an avatar of the room with its own id and a name unique in
the room; its poses go to the room's spectators like a solved batch, but nothing is
solved: they were captured and solved long ago, so their capture, arrival and solve
times are their arrival here. The avatars leave with the connection, at once.
"""

from __future__ import annotations

import secrets
from collections.abc import Callable

import numpy as np

from posecast.protocol import AvatarBatch, AvatarInfo, AvatarRoster, ErrorCode, ProtocolError
from posecast.protocol.pose_coding import RosterCodings
from posecast.server.clock import now
from posecast.server.limits import ServerLimits
from posecast.server.metrics import Metrics
from posecast.server.room import Avatar, Room, SharedBatch


class ReplayedAvatars:
    """The room avatars one replay connection publishes, by the ids of its recording."""

    def __init__(self, room: Room, new_id: Callable[[], int], limits: ServerLimits,
                 metrics: Metrics) -> None:
        self.room = room
        self.new_id = new_id
        self.limits = limits
        self.metrics = metrics
        self.ids: dict[int, int] = {}  # recorded avatar id -> room avatar id
        # the uploaded rosters' codings, by recorded id: how the upload's batches unpack
        self.codings = RosterCodings()

    def roster(self, roster: AvatarRoster) -> None:
        """Avatars to add (or give a new skeleton) and to remove, by recorded id."""
        added = [info for info in roster.avatars if info.avatar_id not in self.ids]
        if len(self.ids) + len(added) > self.limits.players_per_room or (
                len(self.room.avatars) + len(added) > self.limits.avatars_per_room):
            self.metrics.limited["players_per_room"] += 1
            raise ProtocolError(ErrorCode.FULL, f"the room has no place for {len(added)} "
                                                "more avatars")
        self.codings.learn(roster)
        infos = []
        for info in roster.avatars:
            room_id = self.ids.get(info.avatar_id)
            if room_id is None:
                avatar = Avatar(self.new_id(), self.room.unique_name(info.display_name),
                                secrets.token_urlsafe(24))  # a resume no one is given
                self.room.avatars[avatar.avatar_id] = avatar
                self.ids[info.avatar_id] = room_id = avatar.avatar_id
            avatar = self.room.avatars[room_id]
            avatar.info = AvatarInfo(avatar_id=room_id, display_name=avatar.display_name,
                                     joint_names=info.joint_names, parents=info.parents,
                                     rest_offsets=info.rest_offsets, coding=info.coding)
            self.room.keep(avatar, resumable=False)  # for spectators on other processes
            infos.append(avatar.info)
        if infos:
            self.room.broadcast_roster(AvatarRoster(avatars=tuple(infos)))
        for recorded in roster.removed:
            room_id = self.ids.pop(recorded, None)
            if room_id is not None:
                self.room.remove_avatar(room_id)

    def batch(self, batch: AvatarBatch, t_received: float) -> None:
        """The batch's poses to the room's spectators; rows of avatars whose roster did
        not come first, or whose joints are not their skeleton's, are refused."""
        rows, ids = [], []
        for row, recorded in enumerate(batch.avatar_ids.tolist()):
            room_id = self.ids.get(recorded)
            if room_id is None:
                raise ProtocolError(ErrorCode.INVALID, f"avatar_batch.avatar_ids[{row}]: "
                                    f"{recorded} has had no roster: send its skeleton first")
            info = self.room.avatars[room_id].info
            if info is None or int(batch.joint_counts[row]) != info.num_joints:
                raise ProtocolError(ErrorCode.INVALID, f"avatar_batch.joint_counts[{row}]: "
                                    f"{int(batch.joint_counts[row])} joints; its skeleton "
                                    f"has {info.num_joints if info else 0}")
            rows.append(row)
            ids.append(room_id)
        if not rows:
            return
        # its rows passed the spectators' own checks as it was decoded; a recorded pose
        # was captured, received and solved long ago: here, now. One batch per skeleton
        # size (the encoder takes one joint count; a recording has one size, MakeHuman's)
        t_solved = now()
        counts = batch.joint_counts[rows]
        for joints in np.unique(counts).tolist():
            chosen = [r for r, c in zip(rows, counts.tolist(), strict=True) if c == joints]
            frames = [batch.frame(r) for r in chosen]
            room_ids = [ids[rows.index(r)] for r in chosen]
            shared = SharedBatch(room_ids, batch.seqs[chosen].tolist(),
                                 np.array([f.root for f in frames]),
                                 np.array([f.rotations for f in frames]),
                                 [t_received] * len(chosen), [t_received] * len(chosen),
                                 t_solved, codings=self.room.codings(room_ids),
                                 rows_checked=True)
            self.metrics.frames_replayed += len(chosen)
            self.room.deliver(shared)

    def close(self) -> None:
        """The connection ended: its avatars leave the room now."""
        for room_id in self.ids.values():
            self.room.remove_avatar(room_id)
        self.ids.clear()

