"""The browser spectator's JavaScript against the Python it mirrors, run by Node's own
test runner (client/web/test/wire.test.mjs): rotations decoded bit for bit as
protocol/quantize.py decodes them, whole server messages, the clock estimator sample by
sample, the mesh fitted and posed as the desktop viewer does it, each avatar's lost
devices worded as the desktop viewer's HUD words them; and the messages the page sends,
decoded here."""

from __future__ import annotations

import json
from pathlib import Path

import msgpack
import numpy as np
import pytest
from node_js import node_path, run_node_test

from posecast.client.viewer.overlay import device_lines
from posecast.client.viewer.skinning import fit_avatar, pose_matrices
from posecast.protocol import (
    PROTOCOL_VERSION,
    AvatarBatch,
    AvatarInfo,
    AvatarRoster,
    ClockEstimator,
    Error,
    Hello,
    Leave,
    Ping,
    Pong,
    ViewerReport,
    Welcome,
    decode,
    decode_client,
    dequantize_rotations,
    encode,
    quantize_rotations,
)
from posecast.protocol.pose_coding import RosterCodings
from posecast.protocol.roles import DEVICE_ROLES, DeviceRole, role_bits
from posecast.server.avatars import rig_coding
from posecast.server.web import avatar_document
from posecast.solver import rotations as R
from posecast.solver.readers.gltf import load_makehuman
from posecast.solver.rig import build_rig


def unit(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def rotation_cases(rng: np.random.Generator) -> list[dict[str, object]]:
    h = 0.5**0.5
    corners = np.array([[0, 0, 0, 1], [0, 0, 0, -1], [1, 0, 0, 0], [0, h, 0, h],
                        [0.5, 0.5, 0.5, 0.5], [-0.5, 0.5, -0.5, 0.5], [h, h, 0, 0],
                        [0.1, -0.7, 0.7, 0.1]])
    cases = [unit(rng, 200), corners / np.linalg.norm(corners, axis=1, keepdims=True)]
    out = []
    for q in cases:
        wire = quantize_rotations(q)
        out.append({"wire": wire.hex(), "rotations": dequantize_rotations(wire).ravel().tolist()})
    return out


def bad_rotations() -> list[dict[str, str]]:
    good = bytearray(quantize_rotations([[0, 0, 0, 1], [0, 0, 0, 1]]))
    spare = bytearray(good)
    spare[9] |= 0x40  # joint 1's bit 38
    # joint 0: three kept components of 4094 each, 3 x 1/2 > 3/4
    word = (3 << 36) | (4094 << 24) | (4094 << 12) | 4094
    big = word.to_bytes(5, "little") + bytes(good[5:])
    out = []
    for data in (bytes(spare), big, bytes(good[:7])):
        try:
            dequantize_rotations(data)
        except ValueError as err:
            out.append({"wire": data.hex(), "error": str(err)})
    assert len(out) == 3
    return out


# avatar 11 of the batch: its player's frame lacked these (bits 1, 6 and 10)
LOST: tuple[DeviceRole, ...] = ("hip", "left_foot", "chest")


def batch_case(rng: np.random.Generator) -> dict[str, object]:
    batch = AvatarBatch.from_arrays(
        [3, 11], [7, 2**40], np.array([[0.5, 0.9, -1.25], [1e-3, 1.0, 2.0]]),
        [unit(rng, 53), unit(rng, 3)], [10.25, 10.5], [10.3, 10.6], [10.4, 10.7], 10.8,
        lost=[0, role_bits(LOST)])
    wire = encode(batch)
    got = decode(wire)
    assert isinstance(got, AvatarBatch)
    return {"wire": wire.hex(), "values": {
        "lost": got.lost.tolist(), "lost_roles": [list(f.lost_roles) for f in got.frames],
        "avatar_ids": got.avatar_ids.tolist(), "seqs": got.seqs.tolist(),
        "joint_counts": got.joint_counts.tolist(), "roots": got.roots.ravel().tolist(),
        "rotations": got.rotations.ravel().tolist(), "t_capture": got.t_capture.tolist(),
        "t_server_receive": got.t_server_receive.tolist(),
        "t_solved": got.t_solved.tolist(), "t_sent": got.t_sent}}


def bad_messages(batch_wire: bytes) -> list[dict[str, str]]:
    obj = msgpack.unpackb(batch_wire)
    short = dict(obj, rotations=obj["rotations"][:-5])
    far = dict(obj, roots=np.array([[0, 0, 0], [0, 1e4, 0]], "<f4").tobytes())
    nan = dict(obj, capture_age=np.array([1.0, np.nan], "<f4").tobytes())
    twice = dict(obj, avatar_ids=np.array([3, 3], "<i8").tobytes())
    lost_short = dict(obj, lost=obj["lost"][:2])
    lost_beyond = dict(obj, lost=np.array([0, 1 << len(DEVICE_ROLES)], "<u2").tobytes())
    lost_list = dict(obj, lost=[0, 1])
    cases = [(short, "avatar_batch.rotations"), (far, "avatar_batch.roots"),
             (nan, "avatar_batch.capture_age"), (twice, "appears twice"),
             (lost_short, "avatar_batch.lost: expected 4 bytes"),
             (lost_beyond, "avatar_batch.lost: bits beyond the 11 device roles"),
             (lost_list, "avatar_batch.lost: expected 4 bytes"),
             ({"type": "nonsense"}, "unknown message type"), ([1, 2], "a map with")]
    out = [{"wire": msgpack.packb(m, use_bin_type=True).hex(), "words": w} for m, w in cases]
    return [*out, {"wire": batch_wire[:-3].hex(), "words": "not a msgpack message"}]


def clock_cases(rng: np.random.Generator) -> list[dict[str, object]]:
    clock, out = ClockEstimator(), []
    for i in range(60):  # more than the window, and older than its age limit
        t0 = 0.5 * i + rng.uniform(0, 0.01)
        rtt = rng.uniform(-0.001, 0.02)  # now and then a bogus, negative one
        t1 = t0 + 100.0 + rng.uniform(0, max(rtt, 0))
        t2 = t1 + rng.uniform(0, 1e-4)
        t3 = t0 + rtt + (t2 - t1)
        accepted = clock.add(t0, t1, t2, t3)
        out.append({"sample": [t0, t1, t2, t3], "accepted": accepted,
                    "offset": clock.offset, "rtt": clock.rtt if clock.synced else None})
    return out


def skinning_case(rng: np.random.Generator) -> dict[str, object]:
    mesh = load_makehuman()
    sk = mesh.skeleton
    # a person of another build: each bone 0.8-1.25 times the template's; its joints
    # listed breadth first, not in the mesh's order (the page matches them by name)
    order = np.array(sorted(range(sk.num_joints), key=lambda j: (depth(sk.parents, j), j)))
    position = np.argsort(order)
    offsets = sk.offsets * rng.uniform(0.8, 1.25, size=(sk.num_joints, 1))
    info = AvatarInfo(avatar_id=4, display_name="ada",
                      joint_names=tuple(sk.names[j] for j in order),
                      parents=tuple(int(position[sk.parents[j]]) if j else -1 for j in order),
                      rest_offsets=offsets[order])
    fitted = fit_avatar(mesh, info)
    rotations = unit(rng, sk.num_joints)  # in the avatar's order
    root = np.array([0.3, 0.95, -0.2])
    ident = np.broadcast_to(np.eye(4), (sk.num_joints, 4, 4))
    matrices, gq, gp = pose_matrices([fitted], mesh, [rotations], [root])
    a = pose_matrices([fitted], load_without_binds(mesh, ident), [rotations], [root])[0][0]
    h = sk.index("head")
    top = gp[0, h] + R.rotate(gq[0, h], fitted.fit[h] @ sk.tips[h]) + [0.0, 0.12, 0.0]
    assert matrices.shape[0] == 1
    return {"roster": encode(AvatarRoster(avatars=(info,))).hex(),
            "rotations": rotations.tolist(), "root": root.tolist(),
            "matrices": a.tolist(), "anchor": top.tolist()}


def depth(parents: np.ndarray, j: int) -> int:
    return 0 if j == 0 else 1 + depth(parents, int(parents[j]))


def load_without_binds(mesh, inverse_bind):  # type: ignore[no-untyped-def]
    """The mesh with identity inverse binds: its joint matrices are the bones' A_j."""
    import dataclasses

    return dataclasses.replace(mesh, inverse_bind=np.asarray(inverse_bind, np.float32))


@pytest.fixture(scope="module")
def node() -> str:
    return node_path()


def test_the_pages_javascript_speaks_the_python_protocol(node: str, tmp_path: Path) -> None:
    rng = np.random.default_rng(18)
    batch = batch_case(rng)
    fixture = {
        "rotations": rotation_cases(rng), "bad_rotations": bad_rotations(), "batch": batch,
        "bad_messages": bad_messages(bytes.fromhex(batch["wire"])),  # type: ignore[arg-type]
        "roster": roster_case(), "clock": clock_cases(rng), "skinning": skinning_case(rng),
        "coded": coded_case(rng),
        "lost": lost_case(batch),
        "avatar_json": json.loads(avatar_document("/static/avatar.glb")),
        "pong": encode(Pong(t0=1.5, t1=2.25, t2=2.5)).hex(),
        "error": encode(Error(code="invalid", message="hello.room: no")).hex(),
        "welcome": encode(Welcome(protocol_version=PROTOCOL_VERSION, connection_id=1,
                                  avatar_id=None, server_time=5.0)).hex()}
    given, written = tmp_path / "fixture.json", tmp_path / "out.json"
    given.write_text(json.dumps(fixture))
    run_node_test(node, "wire.test.mjs", {"POSECAST_JS_FIXTURE": str(given),
                                          "POSECAST_JS_OUT": str(written)})
    sent = {k: bytes.fromhex(v) for k, v in json.loads(written.read_text()).items()}
    assert decode_client(sent["hello"]) == Hello(
        protocol_version=PROTOCOL_VERSION, role="spectator", room="lab-1",
        display_name="browser", token="a.token")
    assert decode_client(sent["ping"]) == Ping(t0=12.375)
    assert decode_client(sent["leave"]) == Leave(reason="page closed")
    assert decode_client(sent["report"]) == ViewerReport(
        t_capture=[1.0, 2.5], t_received=[1.25, 2.75], t_presented=[1.5, 3.0],
        viewer="browser")
    shown = decode_client(sent["shown"])
    assert isinstance(shown, ViewerReport) and shown.size == 0
    assert (shown.viewer, shown.mode, len(shown.shown)) == ("browser", "predict", 1)
    pose = shown.shown[0]
    assert (pose.avatar_id, pose.t_presented, pose.root.tolist()) == (7, 3.5, [0.1, 0.9, -0.2])
    np.testing.assert_allclose(pose.rotations, [[0, 0, 0, 1], [0.5, -0.5, 0.5, 0.5]],
                               atol=1 / 32767)


def coded_case(rng: np.random.Generator) -> dict[str, object]:
    """Protocol 4: a roster with a MakeHuman avatar's coding, then a batch of it (and of
    one uncoded avatar) packed by it; what Python decodes, and the same bytes spoiled."""
    mesh = load_makehuman()
    sk = mesh.skeleton
    rig = build_rig(sk)
    coding = rig_coding(rig, R.normalize(unit(rng, sk.num_joints)))
    info = AvatarInfo(avatar_id=21, display_name="coded", joint_names=sk.names,
                      parents=tuple(int(p) for p in sk.parents), rest_offsets=sk.offsets,
                      coding=coding)
    codings = RosterCodings()
    roster = encode(AvatarRoster(avatars=(info,)))
    codings.learn(decode(roster))
    poses = np.array([unit(rng, sk.num_joints) for _ in range(2)])
    batch = AvatarBatch.from_arrays([21, 5], [1, 2], np.zeros((2, 3)), list(poses),
                                    [3.0, 3.5], [3.1, 3.6], [3.2, 3.7], 3.25)
    wire = encode(batch, codings)
    got = decode(wire, codings=codings)
    assert isinstance(got, AvatarBatch)
    obj = msgpack.unpackb(wire)
    padding = bytearray(obj["rotations"])
    padding[coding.nbytes - 1] |= 0x80  # past avatar 0's last joint
    spoiled = {"padding": msgpack.packb(dict(obj, rotations=bytes(padding))).hex(),
               "short": msgpack.packb(dict(obj, rotations=obj["rotations"][:-1])).hex()}
    return {"roster": roster.hex(), "wire": wire.hex(), "spoiled": spoiled,
            "rotations": got.rotations.ravel().tolist(), "t_capture": got.t_capture.tolist(),
            "nbytes": coding.nbytes}


def roster_case() -> dict[str, object]:
    info = AvatarInfo(avatar_id=9, display_name="Zoë 2", joint_names=("root", "a", "b"),
                      parents=(-1, 0, 1),
                      rest_offsets=np.array([[0.0, 1.0, 0.0], [0.1, 0.2, 0.3], [0, -0.4, 0]]),
                      devices=("head", "left_hand", "right_hand", "hip"))
    # an older recording's entry names no devices; and one that names an unknown device
    old = {k: v for k, v in info.model_dump().items() if k != "devices"}
    bad = dict(old, devices=["head", "tail"])
    wire = {name: msgpack.packb({"type": "avatar_roster", "avatars": [entry], "removed": []},
                                use_bin_type=True).hex() for name, entry in (("old", old),
                                                                               ("bad", bad))}
    return {"wire": encode(AvatarRoster(avatars=(info,), removed=(2, 5))).hex(),
            "removed": [2, 5], "display_name": "Zoë 2", "joint_names": ["root", "a", "b"],
            "parents": [-1, 0, 1], "rest_offsets": info.rest_offsets.ravel().tolist(),
            "devices": list(info.devices), "old_wire": wire["old"], "bad_wire": wire["bad"]}


def lost_case(batch: dict[str, object]) -> dict[str, object]:
    """The desktop HUD's lines for the batch's avatars (3 with every device, 11 with six
    of them, three lost): the page's must be the same."""
    decoded = decode(bytes.fromhex(str(batch["wire"])))
    assert isinstance(decoded, AvatarBatch)
    infos = [one_joint(3, "player 1", DEVICE_ROLES),
             one_joint(11, "player 2", ("head", "left_hand", "right_hand", *LOST))]
    return {"avatars": [{"name": i.display_name, "devices": list(i.devices)} for i in infos],
            "lines": device_lines(zip(infos, decoded.frames, strict=True))}


def one_joint(avatar_id: int, name: str, devices: tuple[DeviceRole, ...]) -> AvatarInfo:
    return AvatarInfo(avatar_id=avatar_id, display_name=name, joint_names=("root",),
                      parents=(-1,), rest_offsets=np.zeros((1, 3)), devices=devices)
