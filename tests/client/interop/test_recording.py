"""The recording file (client/interop/recording.py): written as messages arrive, read back whole,
and read up to the last whole record when it ends early."""

from __future__ import annotations

from pathlib import Path

import msgpack
import numpy as np
import pytest

from posecast.client.interop.recording import (
    FORMAT,
    RecordingWriter,
    avatar_takes,
    read_recording,
)
from posecast.protocol import AvatarBatch, AvatarInfo, AvatarRoster, decode, encode
from posecast.solver import rotations as R
from posecast.solver.readers.errors import FormatError


def skeleton(avatar_id: int, name: str, joints: int = 3) -> AvatarInfo:
    offsets = np.zeros((joints, 3))
    offsets[1:, 1] = 0.3
    return AvatarInfo(avatar_id=avatar_id, display_name=name,
                      joint_names=tuple(f"j{k}" for k in range(joints)),
                      parents=(-1, *range(joints - 1)), rest_offsets=offsets)


def batch(ids: list[int], t: float, joints: int = 3, seed: int = 0) -> AvatarBatch:
    rng = np.random.default_rng(seed)
    n = len(ids)
    return AvatarBatch.from_arrays(
        ids, [int(t * 90)] * n, rng.normal(size=(n, 3)),
        R.normalize(rng.normal(size=(n, joints, 4))), [t] * n, [t + 0.001] * n, t + 0.002,
        t + 0.003)


def write_session(path: Path) -> list[AvatarBatch]:
    """Two avatars join, stream, one recalibrates with a longer skeleton, one leaves."""
    sent: list[AvatarBatch] = []
    with RecordingWriter(path, "stage", "ws://127.0.0.1:1") as w:
        w.add(0.0, AvatarRoster(avatars=(skeleton(1, "ann"), skeleton(2, "bob"))))
        for k in range(5):
            b = batch([1, 2], 10.0 + k / 90, seed=k)
            w.add(k / 90, b)
            sent.append(decode(encode(b)))  # as a recorder receives it: quantized
        w.add(0.06, AvatarRoster(avatars=(skeleton(2, "bob", joints=4),)))
        for k in range(5, 8):
            b = AvatarBatch.from_arrays([1, 2], [k, k], np.zeros((2, 3)),
                                        [R.identity((3,)), R.identity((4,))], [10.0] * 2,
                                        [10.0] * 2, 10.0, 10.0)
            w.add(k / 90, b)
            sent.append(decode(encode(b)))
        w.add(0.1, AvatarRoster(removed=(1,)))
    return sent


def test_a_recording_reads_back_as_written(tmp_path: Path) -> None:
    path = tmp_path / "s.pcrec"
    sent = write_session(path)
    rec = read_recording(path)
    assert rec.warning is None
    assert rec.header["format"] == FORMAT and rec.room == "stage"
    assert len(rec.messages) == 1 + 5 + 1 + 3 + 1
    got = [m for m in rec.messages if isinstance(m, AvatarBatch)]
    for a, b in zip(got, sent, strict=True):
        assert np.array_equal(a.avatar_ids, b.avatar_ids)
        assert np.array_equal(a.roots, b.roots)
        assert np.array_equal(a.rotations, b.rotations)  # already quantized: exact
        assert np.array_equal(a.t_capture, b.t_capture)
    assert rec.frames() == 16
    assert rec.times[:2] == [0.0, 0.0] and rec.times[-1] == 0.1


def test_takes_split_where_a_skeleton_changes(tmp_path: Path) -> None:
    path = tmp_path / "s.pcrec"
    write_session(path)
    takes = avatar_takes(read_recording(path))
    assert [(t.info.display_name, t.info.num_joints, len(t.times)) for t in takes] == [
        ("ann", 3, 8), ("bob", 3, 5), ("bob", 4, 3)]


def test_a_file_cut_inside_a_record_reads_up_to_the_last_whole_one(tmp_path: Path) -> None:
    path = tmp_path / "s.pcrec"
    write_session(path)
    data = path.read_bytes()
    whole = read_recording(path)
    cut = tmp_path / "cut.pcrec"
    cut.write_bytes(data[:-5])  # the last record (the roster removing ann) loses 5 bytes
    rec = read_recording(cut)
    assert len(rec.messages) == len(whole.messages) - 1
    assert rec.warning is not None and "ends inside record 11" in rec.warning
    assert "read up to record 10" in rec.warning


@pytest.mark.parametrize(("content", "why"), [
    (b"", "empty file"),
    (b"tag rawPosX rawPosY\n", "not a posecast recording"),
    (msgpack.packb({"format": FORMAT, "version": 9}), "recording version 9"),
    (msgpack.packb({"format": FORMAT, "version": 1}) + msgpack.packb([1.0, b"junk"]),
     "record 1:"),
    (msgpack.packb({"format": FORMAT, "version": 1}) + msgpack.packb({"t": 1.0}),
     r"record 1: expected \[time, message bytes\]"),
])
def test_what_is_not_a_recording_is_one_error_naming_the_file(tmp_path: Path, content: bytes,
                                                              why: str) -> None:
    path = tmp_path / "bad.pcrec"
    path.write_bytes(content)
    with pytest.raises(FormatError, match=why) as err:
        read_recording(path)
    assert str(err.value).startswith(str(path))
    assert "\n" not in str(err.value)


def test_a_recording_is_never_written_over(tmp_path: Path) -> None:
    path = tmp_path / "s.pcrec"
    path.write_bytes(b"precious")
    with pytest.raises(FileExistsError):
        RecordingWriter(path, "stage", "ws://x")
    assert path.read_bytes() == b"precious"
