"""The glTF reader against the shipped CC0 MakeHuman rig, and against broken files."""

from __future__ import annotations

import json
import struct
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from posecast.solver import naming, rotations
from posecast.solver.readers.errors import FormatError
from posecast.solver.readers.gltf import SkinnedMesh, load_makehuman, makehuman_path, read_gltf
from posecast.solver.skeleton import Skeleton


@pytest.fixture(scope="module")
def mesh() -> SkinnedMesh:
    return load_makehuman()


def _global_matrices(skeleton: Skeleton, local_rot: NDArray[np.float64]) -> NDArray[np.float64]:
    """Small FK: (J, 4, 4) global joint matrices from (J, 3, 3) local rotations."""
    out = np.zeros((skeleton.num_joints, 4, 4))
    for j in range(skeleton.num_joints):
        local = np.eye(4)
        local[:3, :3] = local_rot[j]
        local[:3, 3] = skeleton.offsets[j]
        p = skeleton.parents[j]
        out[j] = local if p < 0 else out[p] @ local
    return out


def _skin(mesh: SkinnedMesh, globals_: NDArray[np.float64]) -> NDArray[np.float64]:
    """Linear blend skinning of the bind-pose vertices."""
    skin = globals_ @ mesh.inverse_bind.astype(np.float64)  # (J, 4, 4)
    per_vertex = np.einsum("vk,vkab->vab", mesh.weights, skin[mesh.joints])
    homogeneous = np.c_[mesh.positions.astype(np.float64), np.ones(mesh.num_vertices)]
    return np.einsum("vab,vb->va", per_vertex, homogeneous)[:, :3]


def _subtree(skeleton: Skeleton, root: int) -> set[int]:
    out = {root}
    for j in range(root + 1, skeleton.num_joints):  # parents-first: one pass suffices
        if int(skeleton.parents[j]) in out:
            out.add(j)
    return out


def test_sizes_and_arrays(mesh: SkinnedMesh) -> None:
    v = 14_517
    assert mesh.skeleton.num_joints == 53
    assert mesh.positions.shape == (v, 3) and mesh.positions.dtype == np.float32
    assert mesh.normals.shape == (v, 3)
    assert mesh.uvs is not None and mesh.uvs.shape == (v, 2)
    assert mesh.indices.dtype == np.uint32 and len(mesh.indices) % 3 == 0
    assert int(mesh.indices.max()) < v
    assert mesh.joints.shape == (v, 4) and mesh.joints.dtype == np.uint16
    assert int(mesh.joints.max()) < 53
    np.testing.assert_allclose(mesh.weights.sum(axis=1), 1.0, atol=1e-6)
    assert mesh.inverse_bind.shape == (53, 4, 4)
    assert mesh.base_color == pytest.approx((0.8, 0.62, 0.52, 1.0))
    assert not mesh.positions.flags.writeable  # the cached mesh is shared


def test_cached_and_shipped() -> None:
    assert makehuman_path().is_file()
    assert load_makehuman() is load_makehuman()


def test_skeleton_layout(mesh: SkinnedMesh) -> None:
    sk = mesh.skeleton
    assert sk.names[0] == "Root" and sk.parents[0] == -1
    assert all(0 <= sk.parents[j] < j for j in range(1, sk.num_joints))
    roles = naming.roles(sk)
    for role in ("pelvis", "chest", "head", "hand_l", "hand_r", "foot_l", "foot_r",
                 "thigh_l", "upperarm_r", "toes_l"):
        assert role in roles
    rest = sk.rest_positions()
    for foot in ("foot_l", "foot_r"):
        assert 0.05 <= rest[sk.index(foot)][1] <= 0.12
    assert 1.4 <= rest[sk.index("head")][1] <= 1.6
    assert rest[sk.index("thigh_l")][0] > 0 > rest[sk.index("thigh_r")][0]
    # Bind matrices are pure translations to the rest positions.
    np.testing.assert_allclose(mesh.inverse_bind[:, :3, 3], -rest, atol=1e-5)
    np.testing.assert_allclose(mesh.inverse_bind[:, :3, :3], np.broadcast_to(np.eye(3),
                                                                             (53, 3, 3)))


def test_leaf_tips(mesh: SkinnedMesh) -> None:
    sk = mesh.skeleton
    rest = sk.rest_positions()
    leaves = [j for j in range(sk.num_joints) if not sk.children(j)]
    assert len(leaves) == 13  # head, 2 balls, 10 finger ends
    assert np.all(np.linalg.norm(sk.tips[leaves], axis=1) > 0.01)
    inner = [j for j in range(sk.num_joints) if j not in leaves]
    assert not np.any(sk.tips[inner])
    head_top = rest[sk.index("head")] + sk.tips[sk.index("head")]
    assert 1.62 <= head_top[1] <= 1.67  # the crown (the model is 1.666 m tall)
    toe = rest[sk.index("ball_l")] + sk.tips[sk.index("ball_l")]
    assert toe[2] > rest[sk.index("ball_l")][2] and -0.01 <= toe[1] <= 0.04


def test_bind_pose_skinning_reproduces_vertices(mesh: SkinnedMesh) -> None:
    rest_globals = _global_matrices(mesh.skeleton, np.broadcast_to(np.eye(3), (53, 3, 3)))
    np.testing.assert_allclose(_skin(mesh, rest_globals), mesh.positions, atol=1e-5)


def test_upperarm_rotation_moves_only_its_subtree(mesh: SkinnedMesh) -> None:
    sk = mesh.skeleton
    arm = sk.index("upperarm_l")
    local = np.tile(np.eye(3), (sk.num_joints, 1, 1))
    local[arm] = rotations.to_matrix(rotations.from_axis_angle([0.0, 0.0, 1.0],
                                                               np.radians(60.0)))
    posed = _skin(mesh, _global_matrices(sk, local))
    moved = np.linalg.norm(posed - mesh.positions, axis=1) > 1e-6
    subtree = np.array(sorted(_subtree(sk, arm)))
    influenced = np.any(np.isin(mesh.joints, subtree) & (mesh.weights > 0.0), axis=1)
    assert not np.any(moved & ~influenced)  # nothing outside the arm moves
    assert 2_000 <= int(moved.sum()) <= 3_000
    # Left side only (+x): midline vertices (x = 0) carry small shoulder weights, and one
    # right-hand vertex (2288) a stray 0.0006 weight on middle_01_l (it moves < 1 mm).
    visibly = np.linalg.norm(posed - mesh.positions, axis=1) > 1e-3
    assert np.all(mesh.positions[visibly][:, 0] >= 0.0)


def _write_glb(path: Path, doc: bytes, bin_chunk: bytes = b"") -> Path:
    doc += b" " * (-len(doc) % 4)
    chunks = struct.pack("<II", len(doc), 0x4E4F534A) + doc
    if bin_chunk:
        chunks += struct.pack("<II", len(bin_chunk), 0x004E4942) + bin_chunk
    path.write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks)
    return path


def _shipped_json_and_bin() -> tuple[dict[str, Any], bytes]:
    data = makehuman_path().read_bytes()
    (json_len,) = struct.unpack_from("<I", data, 12)
    doc = json.loads(data[20:20 + json_len])
    return doc, data[28 + json_len:]


def test_truncated_file(tmp_path: Path) -> None:
    data = makehuman_path().read_bytes()
    path = tmp_path / "half.glb"
    path.write_bytes(data[:len(data) // 2])
    with pytest.raises(FormatError, match="truncated") as err:
        read_gltf(path)
    assert str(path) in str(err.value)


def test_wrong_magic(tmp_path: Path) -> None:
    data = bytearray(makehuman_path().read_bytes())
    data[:4] = b"GLTF"
    path = tmp_path / "magic.glb"
    path.write_bytes(bytes(data))
    with pytest.raises(FormatError, match="magic") as err:
        read_gltf(path)
    assert str(path) in str(err.value)


def test_corrupt_json(tmp_path: Path) -> None:
    path = _write_glb(tmp_path / "json.glb", b'{"asset": {"version": "2.0"}, "nodes": [')
    with pytest.raises(FormatError, match="JSON") as err:
        read_gltf(path)
    assert str(path) in str(err.value)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(FormatError, match="cannot read"):
        read_gltf(tmp_path / "absent.glb")


@pytest.mark.parametrize(("edit", "message"), [
    (lambda d: d["accessors"][0].update(count=10**6), "reads bytes"),
    (lambda d: d["nodes"][15].update(rotation=[0.0, 0.0, 0.38268343, 0.92387953]),
     "identity rest rotations"),
    (lambda d: d["nodes"][3].update(scale=[2.0, 2.0, 2.0]), "unit scale"),
    (lambda d: d["accessors"][5].update(componentType=5126), "componentType"),
    (lambda d: d.pop("skins"), "skins"),
    (lambda d: d["bufferViews"][0].update(byteOffset=10**7), "bufferViews"),
    (lambda d: d["asset"].update(version="1.0"), "version"),
])
def test_bad_json_content(tmp_path: Path, edit: Callable[[dict[str, Any]], object],
                          message: str) -> None:
    doc, bin_chunk = _shipped_json_and_bin()
    edit(doc)
    path = _write_glb(tmp_path / "bad.glb", json.dumps(doc).encode(), bin_chunk)
    with pytest.raises(FormatError, match=message) as err:
        read_gltf(path)
    assert str(path) in str(err.value)


def test_bad_binary_content(tmp_path: Path) -> None:
    doc, bin_chunk = _shipped_json_and_bin()
    view = doc["bufferViews"][doc["accessors"][5]["bufferView"]]["byteOffset"]
    data = bytearray(bin_chunk)
    data[view:view + 4] = struct.pack("<I", 999_999)  # first triangle index
    path = _write_glb(tmp_path / "index.glb", json.dumps(doc).encode(), bytes(data))
    with pytest.raises(FormatError, match="out of range"):
        read_gltf(path)
    data = bytearray(bin_chunk)
    data[0:4] = struct.pack("<f", float("nan"))  # first vertex x
    path = _write_glb(tmp_path / "nan.glb", json.dumps(doc).encode(), bytes(data))
    with pytest.raises(FormatError, match="non-finite"):
        read_gltf(path)
