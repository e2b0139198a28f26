"""A room recorded as received: the ``.pcrec`` file that ``posecast record`` writes and
``replay`` and ``export`` read.

The file is a stream of msgpack objects, so that it can be written as the session goes
and read back up to wherever it stopped:

- first a header map: ``{"format": "posecast-recording", "version": 1,
  "protocol_version": 1, "room": ..., "server": ..., "created": "<ISO 8601 UTC>"}``;
- then one array per message received, ``[t, message]``: ``t`` the recorder's clock
  (seconds, monotonic, only differences matter) when the message arrived, ``message``
  its protocol encoding (``protocol.codec``): an AvatarRoster (skeletons joining, being
  recalibrated, leaving) or an AvatarBatch (poses, with every timestamp of their way).

Each record is written and flushed whole (and the file synced to disk every
``SYNC_EVERY_S``), so a recorder that crashes loses at most the record it was writing;
a file that ends inside a record reads up to its last whole one, with a warning.
A reader accepts the versions in ``READABLE_VERSIONS`` and says which it found otherwise.
"""

from __future__ import annotations

import datetime
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import msgpack

from posecast.protocol import (
    PROTOCOL_VERSION,
    AvatarBatch,
    AvatarInfo,
    AvatarRoster,
    ProtocolError,
    encode,
)
from posecast.protocol.codec import decode_stream
from posecast.protocol.pose_coding import RosterCodings
from posecast.solver.readers.errors import FormatError

FORMAT = "posecast-recording"
VERSION = 1
READABLE_VERSIONS = frozenset({1})
SUFFIX = ".pcrec"
# a crash loses what the OS has not written: sync at most this often (a sync per record
# would cost a disk write per frame, 90 a second)
SYNC_EVERY_S = 1.0
# a record larger than this is not one a server sent (messages are at most 1 MiB)
MAX_RECORD_BYTES = 2 << 20

RecordedMessage = AvatarRoster | AvatarBatch


class RecordingWriter:
    """Writes a recording as messages arrive; ``close`` (or the ``with`` block) ends it.
    Refuses to overwrite a file: a recording is not something to lose by a typo."""

    def __init__(self, path: Path, room: str, server: str) -> None:
        self.path = path
        self.records = 0
        self.bytes = 0
        self._file: IO[bytes] = open(path, "xb")  # noqa: SIM115 (closed by close())
        self._last_sync = 0.0
        # a batch is written packed as the rosters before it say, as it came: its reader
        # learns the same codings from the same rosters
        self.codings = RosterCodings()
        self._write(msgpack.packb({
            "format": FORMAT, "version": VERSION, "protocol_version": PROTOCOL_VERSION,
            "room": room, "server": server,
            "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        }, use_bin_type=True))

    def add(self, t: float, message: RecordedMessage) -> None:
        """One message as received at ``t`` (the recorder's clock, seconds)."""
        self._write(msgpack.packb([float(t), encode(message, self.codings)],
                                  use_bin_type=True))
        self.codings.learn(message)
        self.records += 1
        if t - self._last_sync >= SYNC_EVERY_S:
            os.fsync(self._file.fileno())
            self._last_sync = t

    def _write(self, data: bytes) -> None:
        self._file.write(data)
        self._file.flush()  # whole records reach the OS: a crash of ours loses none
        self.bytes += len(data)

    def close(self) -> None:
        if not self._file.closed:
            os.fsync(self._file.fileno())
            self._file.close()

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass
class Recording:
    """A recording read back: its header and its messages in order, with arrival times."""

    path: Path
    header: dict[str, Any]
    times: list[float] = field(default_factory=list)
    messages: list[RecordedMessage] = field(default_factory=list)
    warning: str | None = None  # set when the file ends inside a record

    @property
    def room(self) -> str:
        return str(self.header.get("room", ""))

    @property
    def seconds(self) -> float:
        return self.times[-1] - self.times[0] if self.times else 0.0

    def frames(self) -> int:
        """Avatar-frames in the recording (one avatar's pose at one instant)."""
        return sum(len(m.avatar_ids) for m in self.messages if isinstance(m, AvatarBatch))


def read_recording(path: Path) -> Recording:
    """Read a recording; a FormatError (file and record number) if it is not one."""
    src = str(path)
    try:
        data = path.read_bytes()
    except OSError as err:
        raise FormatError(src, None, err.strerror or str(err)) from None
    unpacker = msgpack.Unpacker(raw=False, max_buffer_size=len(data) + 1,
                                max_bin_len=MAX_RECORD_BYTES, strict_map_key=True)
    unpacker.feed(data)
    objects = _objects(unpacker, src)
    header = next(objects, None)
    if header is None:
        raise FormatError(src, None, "empty file: not a posecast recording")
    _check_header(header, src)
    rec = Recording(path, header)
    codings = RosterCodings()
    for index, obj in enumerate(objects, start=1):
        t, message = _record(obj, src, index, codings)
        rec.times.append(t)
        rec.messages.append(message)
    whole = unpacker.tell()
    if whole < len(data):
        rec.warning = (f"{src}: the file ends inside record {len(rec.messages) + 1} "
                       f"({len(data) - whole} bytes of it): read up to record "
                       f"{len(rec.messages)}")
    return rec


def _objects(unpacker: msgpack.Unpacker, src: str) -> Iterator[Any]:
    """The whole msgpack objects of the file, in order; a partial last one ends it."""
    index = 0
    while True:
        try:
            obj = unpacker.unpack()
        except msgpack.OutOfData:
            return
        except (ValueError, msgpack.ExtraData, msgpack.FormatError,
                msgpack.StackError) as err:
            what = "the header" if index == 0 else f"record {index}"
            raise FormatError(src, None, f"{what} is not msgpack ({err}): not a posecast "
                                         "recording, or damaged") from None
        yield obj
        index += 1


def _check_header(header: Any, src: str) -> None:
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise FormatError(src, None, f"not a posecast recording (no {FORMAT!r} header); "
                                     "make one with posecast record")
    version = header.get("version")
    if version not in READABLE_VERSIONS:
        raise FormatError(src, None, f"recording version {version!r}; this posecast reads "
                                     f"version {', '.join(map(str, sorted(READABLE_VERSIONS)))}")


def _record(obj: Any, src: str, index: int, codings: RosterCodings
            ) -> tuple[float, RecordedMessage]:
    if (not isinstance(obj, list) or len(obj) != 2 or type(obj[0]) is not float
            or not isinstance(obj[1], bytes)):
        raise FormatError(src, None, f"record {index}: expected [time, message bytes]")
    try:
        message = decode_stream(obj[1], codings)
    except ProtocolError as err:
        raise FormatError(src, None, f"record {index}: {err.message}") from None
    if not isinstance(message, AvatarRoster | AvatarBatch):
        raise FormatError(src, None, f"record {index}: a {message.type} message; a "
                                     "recording holds rosters and avatar batches")
    return obj[0], message


@dataclass
class AvatarTake:
    """One avatar's motion with one skeleton (a recalibration starts another take)."""

    info: AvatarInfo
    times: list[float] = field(default_factory=list)  # t_capture, server clock, seconds
    roots: list[Any] = field(default_factory=list)  # (3,) arrays
    rotations: list[Any] = field(default_factory=list)  # (J, 4) arrays


def avatar_takes(rec: Recording) -> list[AvatarTake]:
    """Every avatar's poses in the order received, split where its skeleton changed;
    frames of an avatar whose skeleton the recording never saw are left out."""
    current: dict[int, AvatarTake] = {}
    takes: list[AvatarTake] = []
    for message in rec.messages:
        if isinstance(message, AvatarRoster):
            for info in message.avatars:
                take = AvatarTake(info)
                current[info.avatar_id] = take
                takes.append(take)
            for avatar_id in message.removed:
                current.pop(avatar_id, None)
            continue
        for row, avatar_id in enumerate(message.avatar_ids.tolist()):
            found = current.get(avatar_id)
            if found is None:
                continue
            frame = message.frame(row)
            if frame.rotations.shape[0] != found.info.num_joints:
                continue  # a pose for another skeleton (sent before a recalibration)
            found.times.append(frame.t_capture)
            found.roots.append(frame.root)
            found.rotations.append(frame.rotations)
    return [t for t in takes if t.times]
