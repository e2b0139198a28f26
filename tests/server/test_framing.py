"""server/framing.py: the frame built once is the frame websockets would send, and a
spectator's client reads it as any message."""

from __future__ import annotations

import pytest
from websockets.frames import Frame, Opcode

from posecast.server.framing import binary_frame


@pytest.mark.parametrize("size", [0, 1, 125, 126, 127, 65535, 65536, 70000])
def test_a_frame_is_the_one_websockets_builds(size: int) -> None:
    payload = bytes(range(256)) * (size // 256) + bytes(size % 256)
    assert binary_frame(payload) == Frame(Opcode.BINARY, payload).serialize(
        mask=False, extensions=[])
