"""protocol/framing.py: a frame built once is the frame websockets would send, and the
other end's websockets reads it as any message; a read that is one whole frame is taken
as websockets would read it, and only then (``protocol.arrivals.lone_payload``)."""

from __future__ import annotations

import itertools
import secrets

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from websockets.client import ClientProtocol
from websockets.frames import Frame, Opcode
from websockets.protocol import OPEN
from websockets.server import ServerProtocol
from websockets.speedups import apply_mask
from websockets.uri import parse_uri

from posecast.protocol.arrivals import lone_payload
from posecast.protocol.framing import binary_frame, lone_binary_payload, masked_binary_frame

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


# --------------------------------------------------------------------------- reading
def _frame(opcode: Opcode, data: bytes, fin: bool = True) -> bytes:
    return Frame(opcode, data, fin).serialize(mask=True, extensions=[])


def _read(server: ServerProtocol, chunks: list[bytes]) -> list[tuple[Opcode, bytes, bool]]:
    """Each chunk as a connection reads it (``ArrivalStamps.data_received``): taken
    whole where ``lone_payload`` says it is a lone frame, else by websockets. The frames
    read, in order."""
    read: list[tuple[Opcode, bytes, bool]] = []
    for chunk in chunks:
        payload = lone_payload(server, chunk)
        if payload is not None:
            read.append((Opcode.BINARY, payload, True))
            continue
        server.receive_data(chunk)
        read.extend((f.opcode, f.data, f.fin) for f in server.events_received())
    return read


@pytest.mark.parametrize("size", [0, 1, 125, 126, 300, 65535])
def test_a_lone_frame_is_read_whole_and_as_websockets_reads_it(size: int) -> None:
    payload, key = _payload(size), secrets.token_bytes(4)
    data = masked_binary_frame(payload, key)
    assert lone_binary_payload(data, True, None) == payload
    assert lone_binary_payload(binary_frame(payload), False, None) == payload
    for other in (data[:-1], data + data, data[:1], binary_frame(payload)):
        assert lone_binary_payload(other, True, None) is None  # a part, two, unmasked
    assert lone_binary_payload(data, True, size - 1) is None  # over max_size: websockets'
    for frame in (_frame(Opcode.TEXT, payload), _frame(Opcode.PING, payload[:125]),
                  _frame(Opcode.BINARY, payload, fin=False)):
        assert lone_binary_payload(frame, True, None) is None
    rsv = bytes([data[0] | 0x40]) + data[1:]  # a reserved bit: websockets refuses it
    assert lone_binary_payload(rsv, True, None) is None
    assert lone_binary_payload(masked_binary_frame(_payload(65536), key), True, None) is None


def test_a_frame_whose_header_came_alone_is_read_by_websockets() -> None:
    """A read that looks like a whole frame but is the rest of one whose header came
    before (a frame's payload can hold another frame's bytes) is not taken: websockets'
    parser waits within a frame there, not between frames."""
    server = _opened_server()
    inner = masked_binary_frame(b"not a frame of its own", secrets.token_bytes(4))
    outer = masked_binary_frame(b"x" * len(inner), secrets.token_bytes(4))
    head, key = outer[:2], outer[2:6]  # (its length is under 126: a 2-byte header)
    # the outer frame's masked payload is made to be the inner frame's bytes
    read = _read(server, [head + key, inner])
    assert read == [(Opcode.BINARY, apply_mask(inner, key), True)]
    # and the next read that is a whole frame of its own is taken whole again
    assert lone_payload(server, masked_binary_frame(b"next", secrets.token_bytes(4))) \
        == b"next"


def test_a_lone_binary_frame_within_a_fragmented_message_is_left_to_websockets() -> None:
    server = _opened_server()
    assert _read(server, [_frame(Opcode.BINARY, b"part", fin=False)]) == [
        (Opcode.BINARY, b"part", False)]
    assert lone_payload(server, masked_binary_frame(b"x", secrets.token_bytes(4))) is None
    server.receive_data(masked_binary_frame(b"x", secrets.token_bytes(4)))
    assert server.close_sent is not None and server.close_sent.code == 1002


_FRAMES = st.lists(st.one_of(
    st.tuples(st.just(Opcode.BINARY), st.binary(max_size=300)),
    st.tuples(st.just(Opcode.TEXT), st.text(max_size=40).map(str.encode)),
    st.tuples(st.just(Opcode.PING), st.binary(max_size=20)),
    st.tuples(st.just(Opcode.CONT), st.binary(max_size=50))),  # a fragmented message
    max_size=12)


@settings(max_examples=300, deadline=None)
@given(frames=_FRAMES, cuts=st.lists(st.integers(min_value=0, max_value=4000), max_size=12),
       lone=st.booleans())
def test_any_stream_cut_anywhere_reads_as_websockets_reads_it(
        frames: list[tuple[Opcode, bytes]], cuts: list[int], lone: bool) -> None:
    """Frames of every kind (a CONT entry sends a message in two fragments, a ping
    between them), the stream cut anywhere or each frame its own read: the frames read
    are the frames sent, in order, and the connection stays open."""
    sent: list[tuple[Opcode, bytes, bool]] = []
    for opcode, data in frames:
        if opcode is Opcode.CONT:
            sent += [(Opcode.BINARY, data[:9], False), (Opcode.PING, b"p", True),
                     (Opcode.CONT, data[9:], True)]
        else:
            sent.append((opcode, data, True))
    wire = [_frame(o, d, fin) for o, d, fin in sent]
    if lone:
        chunks = wire
    else:
        stream = b"".join(wire)
        bounds = sorted({0, len(stream), *(c for c in cuts if c < len(stream))})
        chunks = [stream[a:b] for a, b in itertools.pairwise(bounds)]
    server = _opened_server()
    assert _read(server, chunks) == sent
    assert server.state is OPEN and server.close_sent is None
