"""protocol/framing.py: a frame built once is the frame websockets would send, and the
other end's websockets reads it as any message."""

from __future__ import annotations

import secrets

import pytest
from websockets.client import ClientProtocol
from websockets.frames import Frame, Opcode
from websockets.protocol import OPEN
from websockets.server import ServerProtocol
from websockets.uri import parse_uri

from posecast.protocol.framing import binary_frame, masked_binary_frame

SIZES = [0, 1, 125, 126, 127, 65535, 65536, 70000]


def _payload(size: int) -> bytes:
    return bytes(range(256)) * (size // 256) + bytes(size % 256)


@pytest.mark.parametrize("size", SIZES)
def test_a_frame_is_the_one_websockets_builds(size: int) -> None:
    payload = _payload(size)
    assert binary_frame(payload) == Frame(Opcode.BINARY, payload).serialize(
        mask=False, extensions=[])


@pytest.mark.parametrize("size", SIZES)
def test_a_masked_frame_is_the_one_websockets_builds_with_that_key(
        size: int, monkeypatch: pytest.MonkeyPatch) -> None:
    payload, key = _payload(size), bytes([0x37, 0xFA, 0x21, 0x3D])
    monkeypatch.setattr(secrets, "token_bytes", lambda n: key)  # websockets' key source
    assert masked_binary_frame(payload, key) == Frame(Opcode.BINARY, payload).serialize(
        mask=True, extensions=[])


def _opened_server(max_size: int | None = None) -> ServerProtocol:
    """websockets' own server side (as a posecast server reads a player's socket), past
    a real opening handshake."""
    client, server = ClientProtocol(parse_uri("ws://127.0.0.1/")), ServerProtocol(
        max_size=max_size)
    client.send_request(client.connect())
    server.receive_data(b"".join(client.data_to_send()))
    (request,) = server.events_received()
    server.send_response(server.accept(request))
    assert server.state is OPEN
    return server


def test_a_server_reads_a_players_frames_as_its_messages() -> None:
    server = _opened_server()
    messages = [b"", b"\x81\x00tracker frame", _payload(300), _payload(70000)]
    server.receive_data(b"".join(masked_binary_frame(m, secrets.token_bytes(4))
                                 for m in messages))
    frames = server.events_received()
    assert [(f.opcode, f.data) for f in frames] == [(Opcode.BINARY, m) for m in messages]
    assert server.state is OPEN


def test_a_server_closes_on_an_unmasked_client_frame() -> None:
    server = _opened_server()
    server.receive_data(binary_frame(b"not masked"))
    assert server.events_received() == [] and server.close_rcvd is None
    assert server.close_sent is not None and server.close_sent.code == 1002  # protocol error


def test_a_masking_key_is_four_bytes() -> None:
    with pytest.raises(ValueError, match="4 bytes, not 3"):
        masked_binary_frame(b"x", b"abc")
