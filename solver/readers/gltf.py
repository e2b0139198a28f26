"""Read a skinned, rigged avatar mesh from a glTF 2.0 binary file (.glb).

The viewer skins avatars on the GPU and the solver needs the avatar's skeleton; both come
from one file, the CC0 MakeHuman rig shipped in ``solver/assets`` (see its README). The GLB
container is simple enough to parse with struct, json and numpy, so no glTF library is
needed: a 12-byte header, a JSON chunk, a BIN chunk, and accessors that point through
bufferViews at byte ranges of the BIN chunk.

What is supported, and what is rejected with a ``FormatError`` (line None, the byte offset
or the JSON path in the message):

- One skinned mesh: the first node that has both ``mesh`` and ``skin``. Its primitives
  (triangles only) are concatenated; the base colour is the first primitive's material.
- The bind pose must be the node rest pose with identity rotations and unit scales, because
  ``Skeleton`` assumes identity rest rotations: every joint node (and every node above one)
  must have identity rotation and unit scale, and every inverse bind matrix must be the pure
  translation to its joint's rest position.
- Only the embedded BIN buffer (no external or data URIs), no sparse accessors.
- Up to any number of JOINTS_n/WEIGHTS_n sets; the four largest influences per vertex are
  kept and renormalised to sum to 1.
"""

from __future__ import annotations

import functools
import heapq
import json
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

import numpy as np
from numpy.typing import NDArray

from posecast.solver.readers.errors import FormatError
from posecast.solver.skeleton import Skeleton, SkeletonError

MAKEHUMAN_ASSET = "MakeHuman_hm08_game_engine_CC0.glb"
DEFAULT_BASE_COLOR = (0.8, 0.8, 0.8, 1.0)

_MAGIC = b"glTF"
_CHUNK_JSON = 0x4E4F534A
_CHUNK_BIN = 0x004E4942
_COMPONENTS: dict[int, type[np.generic]] = {
    5120: np.int8, 5121: np.uint8, 5122: np.int16,
    5123: np.uint16, 5125: np.uint32, 5126: np.float32,
}
_FLOAT = 5126
_UNSIGNED = (5121, 5123, 5125)
_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}
_TRIANGLES = 4
_INFLUENCES = 4
# Rest rotations/scales and bind matrices are float32 in most files: allow that noise.
_IDENTITY_TOL = 1e-5
_BIND_TOL_M = 1e-4
# A vertex belongs to a leaf bone's flesh when the bone carries more than this weight.
_TIP_WEIGHT = 0.5
# A leaf's tip is the centre of the flesh reaching beyond this fraction of its farthest reach.
_TIP_CAP = 0.9


@dataclass(frozen=True, eq=False)
class SkinnedMesh:
    """A skinned mesh in its bind pose. Arrays are read-only (the shipped one is cached)."""

    skeleton: Skeleton  # the skin's joints, parents-first (see ``read_gltf``)
    positions: NDArray[np.float32]  # (V, 3) bind-pose vertex positions, metres
    normals: NDArray[np.float32]  # (V, 3)
    uvs: NDArray[np.float32] | None  # (V, 2), None when a primitive has no TEXCOORD_0
    indices: NDArray[np.uint32]  # (T*3,) triangle vertex indices
    joints: NDArray[np.uint16]  # (V, 4) indices into ``skeleton`` (not into the skin)
    weights: NDArray[np.float32]  # (V, 4), rows sum to 1
    inverse_bind: NDArray[np.float32]  # (J, 4, 4) skeleton order, v_bone = IB @ v_world
    base_color: tuple[float, float, float, float]  # baseColorFactor, linear RGBA

    @property
    def num_vertices(self) -> int:
        return int(self.positions.shape[0])


class _Glb:
    """The parsed container: JSON document, BIN chunk, and error reporting for one file."""

    def __init__(self, path: str, doc: dict[str, Any], bin_chunk: bytes) -> None:
        self.path = path
        self.doc = doc
        self.bin = bin_chunk

    def fail(self, message: str) -> NoReturn:
        raise FormatError(self.path, None, message)

    def array(self, key: str) -> list[Any]:
        value = self.doc.get(key)
        if not isinstance(value, list):
            self.fail(f"JSON: $.{key} is missing or not an array")
        return value

    def item(self, key: str, index: Any, where: str) -> dict[str, Any]:
        items = self.array(key)
        if not _is_int(index) or not 0 <= index < len(items):
            self.fail(f"JSON: {where} refers to {key}[{index}], but there are {len(items)}")
        obj = items[index]
        if not isinstance(obj, dict):
            self.fail(f"JSON: $.{key}[{index}] is not an object")
        return obj

    def get(self, obj: dict[str, Any], key: str, where: str, kind: type | tuple[type, ...],
            default: Any = None) -> Any:
        """obj[key] checked against kind; default when absent (None: the key is required)."""
        if key not in obj:
            if default is None:
                self.fail(f"JSON: {where}.{key} is required but missing")
            return default
        value = obj[key]
        if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
            self.fail(f"JSON: {where}.{key} has the wrong type ({type(value).__name__})")
        return value

    def numbers(self, obj: dict[str, Any], key: str, where: str, n: int,
                default: tuple[float, ...]) -> NDArray[np.float64]:
        """A fixed-length array of finite numbers, default when absent."""
        value = obj.get(key, default)
        ok = (isinstance(value, list | tuple) and len(value) == n
              and all(isinstance(v, int | float) and not isinstance(v, bool) for v in value))
        if not ok:
            self.fail(f"JSON: {where}.{key} must be an array of {n} numbers")
        out = np.asarray(value, dtype=np.float64)
        if not np.all(np.isfinite(out)):
            self.fail(f"JSON: {where}.{key} holds non-finite numbers")
        return out


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


# ---------------------------------------------------------------------------- container


def _split_glb(path: str, data: bytes) -> _Glb:
    """Check the 12-byte header and walk the chunks: JSON first, then an optional BIN."""
    if len(data) < 12:
        raise FormatError(path, None, f"file is {len(data)} bytes, too short for a GLB header")
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    if magic != _MAGIC:
        raise FormatError(path, None, f"byte 0: magic is {magic!r}, not b'glTF': not a GLB file")
    if version != 2:
        raise FormatError(path, None, f"byte 4: glTF container version {version}, expected 2")
    if length > len(data):
        raise FormatError(path, None, f"byte 8: header declares {length} bytes but the file "
                                      f"has {len(data)}: the file is truncated")
    chunks: list[tuple[int, int, bytes]] = []
    offset = 12
    while offset < length:
        if offset + 8 > length:
            raise FormatError(path, None, f"byte {offset}: chunk header runs past the end")
        size, kind = struct.unpack_from("<II", data, offset)
        if offset + 8 + size > length:
            raise FormatError(path, None, f"byte {offset}: chunk of {size} bytes runs past "
                                          f"the end of the file ({length} bytes)")
        chunks.append((offset, kind, data[offset + 8:offset + 8 + size]))
        offset += 8 + size
    if not chunks or chunks[0][1] != _CHUNK_JSON:
        raise FormatError(path, None, "byte 12: the first chunk must be the JSON chunk")
    doc = _parse_json(path, chunks[0][2])
    # Unknown chunk types are skipped, as the spec asks; the BIN chunk, if any, is second.
    bin_chunk = chunks[1][2] if len(chunks) > 1 and chunks[1][1] == _CHUNK_BIN else b""
    return _Glb(path, doc, bin_chunk)


def _parse_json(path: str, raw: bytes) -> dict[str, Any]:
    try:
        doc = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise FormatError(path, None, f"JSON chunk (byte 20) does not parse: {err}") from None
    if not isinstance(doc, dict):
        raise FormatError(path, None, "JSON: the document is not an object")
    asset = doc.get("asset")
    version = asset.get("version") if isinstance(asset, dict) else None
    if not isinstance(version, str) or not version.startswith("2."):
        raise FormatError(path, None, f"JSON: $.asset.version is {version!r}, expected '2.x'")
    return doc


# ---------------------------------------------------------------------------- accessors


def _accessor(g: _Glb, index: Any, where: str, types: tuple[str, ...],
              components: tuple[int, ...]) -> NDArray[Any]:
    """Accessor ``index`` as a (count, width) array; normalized integers become float32."""
    acc = g.item("accessors", index, where)
    aw = f"$.accessors[{index}]"
    ctype = g.get(acc, "componentType", aw, int)
    kind = g.get(acc, "type", aw, str)
    count = g.get(acc, "count", aw, int)
    if ctype not in components:
        g.fail(f"JSON: {aw} (used by {where}) has componentType {ctype}, "
               f"expected one of {list(components)}")
    if kind not in types:
        g.fail(f"JSON: {aw} (used by {where}) has type {kind!r}, expected one of {list(types)}")
    if count < 1:
        g.fail(f"JSON: {aw}.count is {count}, must be at least 1")
    if "sparse" in acc:
        g.fail(f"JSON: {aw} is a sparse accessor, which this reader does not support")
    dtype = np.dtype(_COMPONENTS[ctype]).newbyteorder("<")
    width = _WIDTHS[kind]
    if "bufferView" in acc:
        out = _view_elements(g, acc, aw, dtype, width, count)
    else:
        out = np.zeros((count, width), dtype)  # the spec: no bufferView means zeros
    if g.get(acc, "normalized", aw, bool, False) and ctype != _FLOAT:
        out = _denormalize(out)
    if out.dtype.kind == "f" and not np.all(np.isfinite(out)):
        g.fail(f"{aw} (used by {where}) holds non-finite numbers (NaN or inf)")
    return out


def _view_elements(g: _Glb, acc: dict[str, Any], aw: str, dtype: np.dtype[Any], width: int,
                   count: int) -> NDArray[Any]:
    """Copy ``count`` elements out of the accessor's bufferView, honouring byteStride."""
    view_index = acc["bufferView"]
    view = g.item("bufferViews", view_index, aw)
    vw = f"$.bufferViews[{view_index}]"
    view_start, view_length = _view_range(g, view, vw)
    start = g.get(acc, "byteOffset", aw, int, 0)
    element = dtype.itemsize * width
    stride = g.get(view, "byteStride", vw, int, element)
    if start < 0 or stride < element:
        g.fail(f"JSON: {aw} has byteOffset {start} and stride {stride} for {element}-byte "
               f"elements: impossible")
    end = start + stride * (count - 1) + element
    if end > view_length:
        g.fail(f"{aw} reads bytes {start}..{end} of {vw}, which holds only {view_length} bytes")
    raw = np.ndarray((count, width), dtype, buffer=g.bin, offset=view_start + start,
                     strides=(stride, dtype.itemsize))
    return raw.astype(dtype.newbyteorder("="), copy=True)


def _view_range(g: _Glb, view: dict[str, Any], vw: str) -> tuple[int, int]:
    """Absolute start in the BIN chunk and length of a bufferView, checked in range."""
    buffer_index = g.get(view, "buffer", vw, int)
    buffer = g.item("buffers", buffer_index, vw)
    bw = f"$.buffers[{buffer_index}]"
    if "uri" in buffer or buffer_index != 0:
        g.fail(f"JSON: {bw} is not the embedded BIN chunk; external buffers are not supported")
    declared = g.get(buffer, "byteLength", bw, int)
    if declared > len(g.bin):
        g.fail(f"JSON: {bw}.byteLength is {declared} but the BIN chunk holds {len(g.bin)} bytes")
    offset = g.get(view, "byteOffset", vw, int, 0)
    length = g.get(view, "byteLength", vw, int)
    if offset < 0 or length < 0 or offset + length > declared:
        g.fail(f"JSON: {vw} covers bytes {offset}..{offset + length} of {bw}, "
               f"which has {declared}")
    return offset, length


def _denormalize(values: NDArray[Any]) -> NDArray[np.float32]:
    """glTF normalized integers to float: unsigned to [0, 1], signed to [-1, 1]."""
    info = np.iinfo(values.dtype)
    out = values.astype(np.float32) / np.float32(info.max)
    return np.maximum(out, np.float32(-1.0))


# ---------------------------------------------------------------------------- nodes


def _node_parents(g: _Glb) -> dict[int, int]:
    """child node -> parent node, checking that no node has two parents."""
    nodes = g.array("nodes")
    parents: dict[int, int] = {}
    for i in range(len(nodes)):
        node = g.item("nodes", i, "$.nodes")
        for child in g.get(node, "children", f"$.nodes[{i}]", list, []):
            if not _is_int(child) or not 0 <= child < len(nodes):
                g.fail(f"JSON: $.nodes[{i}].children lists {child!r}, not a node index")
            if child in parents:
                g.fail(f"JSON: $.nodes[{child}] is a child of nodes {parents[child]} and {i}")
            parents[child] = i
    return parents


def _rest_translation(g: _Glb, index: int, role: str) -> NDArray[np.float64]:
    """A node's translation, after checking it neither rotates nor scales."""
    node = g.item("nodes", index, "$.nodes")
    nw = f"$.nodes[{index}]"
    name = node.get("name", nw)
    if "matrix" in node:
        m = g.numbers(node, "matrix", nw, 16, ()).reshape(4, 4).T  # column-major in glTF
        if not np.allclose(m[:3, :3], np.eye(3), atol=_IDENTITY_TOL) or not np.allclose(
                m[3], (0, 0, 0, 1), atol=_IDENTITY_TOL):
            g.fail(f"{nw} ({name!r}, {role}) has a matrix that rotates or scales; Skeleton "
                   f"assumes identity rest rotations and unit scale")
        return m[:3, 3].copy()
    rotation = g.numbers(node, "rotation", nw, 4, (0.0, 0.0, 0.0, 1.0))
    scale = g.numbers(node, "scale", nw, 3, (1.0, 1.0, 1.0))
    if np.max(np.abs(rotation[:3])) > _IDENTITY_TOL or abs(abs(rotation[3]) - 1) > _IDENTITY_TOL:
        g.fail(f"{nw} ({name!r}, {role}) has rest rotation {rotation.tolist()}; Skeleton "
               f"assumes identity rest rotations")
    if np.max(np.abs(scale - 1.0)) > _IDENTITY_TOL:
        g.fail(f"{nw} ({name!r}, {role}) has scale {scale.tolist()}; Skeleton assumes unit "
               f"scale")
    return g.numbers(node, "translation", nw, 3, (0.0, 0.0, 0.0))


def _global_position(g: _Glb, node: int, parents: dict[int, int],
                     joints: set[int]) -> NDArray[np.float64]:
    """World rest position of a node: the sum of translations up to the scene root."""
    total = np.zeros(3)
    seen: set[int] = set()
    current: int | None = node
    while current is not None:
        if current in seen:
            g.fail(f"JSON: the node hierarchy has a cycle through $.nodes[{current}]")
        seen.add(current)
        role = "a joint" if current in joints else "an ancestor of a joint"
        total += _rest_translation(g, current, role)
        current = parents.get(current)
    return total


def _skin_parent(node: int, parents: dict[int, int], joints: set[int]) -> int | None:
    """The nearest ancestor node that is a joint of the skin (None for the skin's root)."""
    current = parents.get(node)
    seen = {node}
    while current is not None and current not in joints and current not in seen:
        seen.add(current)
        current = parents.get(current)
    return current if current in joints else None


def _parents_first(skin_parents: list[int | None]) -> list[int]:
    """Skin indices in skeleton order: skin order, except that a joint listed before its
    parent waits until the parent is placed (Kahn's sort, lowest skin index first)."""
    children: dict[int, list[int]] = {}
    ready: list[int] = []
    for k, p in enumerate(skin_parents):
        if p is None:
            ready.append(k)
        else:
            children.setdefault(p, []).append(k)
    order: list[int] = []
    while ready:
        k = heapq.heappop(ready)
        order.append(k)
        for c in children.get(k, []):
            heapq.heappush(ready, c)
    return order


# ---------------------------------------------------------------------------- skin


def _skinned_node(g: _Glb) -> tuple[int, int]:
    """(mesh index, skin index) of the first node carrying both."""
    nodes = g.array("nodes")
    for i in range(len(nodes)):
        node = g.item("nodes", i, "$.nodes")
        if "mesh" in node and "skin" in node:
            return (g.get(node, "mesh", f"$.nodes[{i}]", int),
                    g.get(node, "skin", f"$.nodes[{i}]", int))
    g.fail("JSON: no node has both a mesh and a skin: not a skinned mesh")


def _skin_skeleton(g: _Glb, skin_index: int) -> tuple[Skeleton, list[int], NDArray[np.float32]]:
    """The skin's joints as a Skeleton, the skin index of each skeleton joint, and the
    inverse bind matrices in skeleton order (column-vector convention)."""
    skin = g.item("skins", skin_index, "a skinned node")
    sw = f"$.skins[{skin_index}]"
    joint_nodes = g.get(skin, "joints", sw, list)
    nodes = g.array("nodes")
    if not joint_nodes or any(not _is_int(n) or not 0 <= n < len(nodes) for n in joint_nodes):
        g.fail(f"JSON: {sw}.joints must be a non-empty list of node indices")
    if len(set(joint_nodes)) != len(joint_nodes):
        g.fail(f"JSON: {sw}.joints lists a node twice")
    parents = _node_parents(g)
    node_set = set(joint_nodes)
    # Positions first: walking to the scene root also rejects cycles in the hierarchy.
    position = {k: _global_position(g, n, parents, node_set) for k, n in enumerate(joint_nodes)}
    skin_of_node = {n: k for k, n in enumerate(joint_nodes)}
    skin_parents = [_skin_parent(n, parents, node_set) for n in joint_nodes]
    roots = [joint_nodes[k] for k, p in enumerate(skin_parents) if p is None]
    if len(roots) != 1:
        g.fail(f"JSON: {sw} has {len(roots)} root joints (nodes {roots}); Skeleton needs one")
    skin_parent_idx = [None if p is None else skin_of_node[p] for p in skin_parents]
    order = _parents_first(skin_parent_idx)
    rank = {k: j for j, k in enumerate(order)}
    names, parent_idx, offsets = [], [], []
    for k in order:
        p = skin_parent_idx[k]
        node = g.item("nodes", joint_nodes[k], sw)
        names.append(str(node.get("name", f"joint_{k}")))
        parent_idx.append(-1 if p is None else rank[p])
        # The root keeps its world position so rest_positions() are the bind positions.
        offsets.append(position[k] if p is None else position[k] - position[p])
    try:
        skeleton = Skeleton(tuple(names), np.array(parent_idx, np.int32), np.array(offsets))
    except SkeletonError as err:
        g.fail(f"{sw}: {err}")
    inverse_bind = _inverse_bind(g, skin, sw, len(joint_nodes))[order]
    _check_bind(g, skeleton, inverse_bind)
    return skeleton, order, inverse_bind


def _inverse_bind(g: _Glb, skin: dict[str, Any], sw: str, n: int) -> NDArray[np.float32]:
    """(n, 4, 4) inverse bind matrices in skin order; identity when absent (the spec)."""
    if "inverseBindMatrices" not in skin:
        return np.tile(np.eye(4, dtype=np.float32), (n, 1, 1))
    flat = _accessor(g, skin["inverseBindMatrices"], f"{sw}.inverseBindMatrices",
                     ("MAT4",), (_FLOAT,))
    if len(flat) < n:
        g.fail(f"JSON: {sw}.inverseBindMatrices has {len(flat)} matrices for {n} joints")
    # glTF stores matrices column-major: reshape gives the transpose of each matrix.
    return np.ascontiguousarray(flat[:n].reshape(n, 4, 4).transpose(0, 2, 1))


def _check_bind(g: _Glb, skeleton: Skeleton, inverse_bind: NDArray[np.float32]) -> None:
    """Each inverse bind matrix must undo its joint's rest position and nothing more, else
    the node rest pose (the Skeleton's) is not the pose the mesh was bound in."""
    rest = skeleton.rest_positions()
    for j, name in enumerate(skeleton.names):
        m = inverse_bind[j].astype(np.float64)
        if not (np.allclose(m[:3, :3], np.eye(3), atol=_IDENTITY_TOL)
                and np.allclose(m[3], (0, 0, 0, 1), atol=_IDENTITY_TOL)):
            g.fail(f"inverse bind matrix of joint {name!r} rotates or scales; Skeleton needs "
                   f"identity bind rotations (pure-translation inverse bind matrices)")
        if np.max(np.abs(m[:3, 3] + rest[j])) > _BIND_TOL_M:
            g.fail(f"inverse bind matrix of joint {name!r} binds it at {(-m[:3, 3]).tolist()}, "
                   f"but its node rest position is {rest[j].tolist()}: the bind pose must be "
                   f"the node rest pose")


# ---------------------------------------------------------------------------- mesh


@dataclass
class _Primitive:
    positions: NDArray[np.float32]
    normals: NDArray[np.float32]
    uvs: NDArray[np.float32] | None
    indices: NDArray[np.uint32]
    joints: NDArray[np.uint16]  # skin indices
    weights: NDArray[np.float32]
    material: int | None


def _read_primitive(g: _Glb, prim: dict[str, Any], pw: str, num_joints: int) -> _Primitive:
    if g.get(prim, "mode", pw, int, _TRIANGLES) != _TRIANGLES:
        g.fail(f"JSON: {pw}.mode is {prim['mode']}: only triangle lists (4) are supported")
    attrs = g.get(prim, "attributes", pw, dict)
    aw = f"{pw}.attributes"
    positions = _accessor(g, g.get(attrs, "POSITION", aw, int), f"{aw}.POSITION",
                          ("VEC3",), (_FLOAT,))
    count = len(positions)
    indices = _read_indices(g, prim, pw, count)
    normals = (_attribute(g, attrs, "NORMAL", aw, ("VEC3",), (_FLOAT,), count)
               if "NORMAL" in attrs else _vertex_normals(positions, indices))
    uvs = (_attribute(g, attrs, "TEXCOORD_0", aw, ("VEC2",), (_FLOAT, 5121, 5123), count)
           if "TEXCOORD_0" in attrs else None)
    joints, weights = _read_influences(g, attrs, aw, count, num_joints)
    material = g.get(prim, "material", pw, int, -1)
    return _Primitive(positions.astype(np.float32), normals.astype(np.float32),
                      None if uvs is None else uvs.astype(np.float32), indices, joints,
                      weights, None if material < 0 else material)


def _attribute(g: _Glb, attrs: dict[str, Any], key: str, aw: str, types: tuple[str, ...],
               components: tuple[int, ...], count: int) -> NDArray[Any]:
    values = _accessor(g, g.get(attrs, key, aw, int), f"{aw}.{key}", types, components)
    if len(values) != count:
        g.fail(f"JSON: {aw}.{key} has {len(values)} elements for {count} vertices")
    return values


def _read_indices(g: _Glb, prim: dict[str, Any], pw: str, count: int) -> NDArray[np.uint32]:
    if "indices" not in prim:
        indices = np.arange(count, dtype=np.uint32)  # non-indexed: vertices in order
    else:
        indices = _accessor(g, prim["indices"], f"{pw}.indices", ("SCALAR",),
                            _UNSIGNED).ravel().astype(np.uint32)
    if len(indices) % 3:
        g.fail(f"JSON: {pw}.indices has {len(indices)} entries, not a multiple of 3")
    if len(indices) and int(indices.max()) >= count:
        g.fail(f"{pw}.indices: index {int(indices.max())} is out of range for {count} vertices")
    return indices


def _read_influences(g: _Glb, attrs: dict[str, Any], aw: str, count: int,
                     num_joints: int) -> tuple[NDArray[np.uint16], NDArray[np.float32]]:
    """All JOINTS_n/WEIGHTS_n sets, reduced to the four largest weights, renormalised."""
    joint_sets, weight_sets = [], []
    n = 0
    while f"JOINTS_{n}" in attrs or f"WEIGHTS_{n}" in attrs:
        joint_sets.append(_attribute(g, attrs, f"JOINTS_{n}", aw, ("VEC4",), (5121, 5123),
                                     count))
        weight_sets.append(_attribute(g, attrs, f"WEIGHTS_{n}", aw, ("VEC4",),
                                      (_FLOAT, 5121, 5123), count))
        n += 1
    if not joint_sets:
        g.fail(f"JSON: {aw} has no JOINTS_0/WEIGHTS_0: the mesh is not skinned")
    joints = np.concatenate(joint_sets, axis=1).astype(np.int64)
    weights = np.concatenate(weight_sets, axis=1).astype(np.float64)
    if int(joints.max()) >= num_joints:
        g.fail(f"{aw}.JOINTS_n: joint index {int(joints.max())} is out of range for a skin of "
               f"{num_joints} joints")
    if float(weights.min()) < 0.0:
        g.fail(f"{aw}.WEIGHTS_n: vertex {int(np.argmin(weights.min(axis=1)))} has a negative "
               f"weight")
    if joints.shape[1] > _INFLUENCES:
        keep = np.argsort(-weights, axis=1, kind="stable")[:, :_INFLUENCES]
        joints = np.take_along_axis(joints, keep, axis=1)
        weights = np.take_along_axis(weights, keep, axis=1)
    total = weights.sum(axis=1)
    if float(total.min()) <= 0.0:
        g.fail(f"{aw}.WEIGHTS_0: vertex {int(np.argmin(total))} has weights summing to 0")
    return joints.astype(np.uint16), (weights / total[:, None]).astype(np.float32)


def _vertex_normals(positions: NDArray[Any], indices: NDArray[np.uint32]) -> NDArray[np.float32]:
    """Area-weighted vertex normals, for primitives that store none."""
    p = positions.astype(np.float64)
    tri = indices.reshape(-1, 3).astype(np.int64)
    face = np.cross(p[tri[:, 1]] - p[tri[:, 0]], p[tri[:, 2]] - p[tri[:, 0]])
    normals = np.zeros_like(p)
    for corner in range(3):
        np.add.at(normals, tri[:, corner], face)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return (normals / np.where(length > 0.0, length, 1.0)).astype(np.float32)


def _read_mesh(g: _Glb, mesh_index: int, num_joints: int) -> list[_Primitive]:
    mesh = g.item("meshes", mesh_index, "a skinned node")
    mw = f"$.meshes[{mesh_index}]"
    primitives = g.get(mesh, "primitives", mw, list)
    if not primitives:
        g.fail(f"JSON: {mw}.primitives is empty")
    out = []
    for i, prim in enumerate(primitives):
        if not isinstance(prim, dict):
            g.fail(f"JSON: {mw}.primitives[{i}] is not an object")
        out.append(_read_primitive(g, prim, f"{mw}.primitives[{i}]", num_joints))
    return out


def _base_color(g: _Glb, material: int | None) -> tuple[float, float, float, float]:
    if material is None:
        return DEFAULT_BASE_COLOR
    mat = g.item("materials", material, "a primitive")
    mw = f"$.materials[{material}]"
    pbr = g.get(mat, "pbrMetallicRoughness", mw, dict, {})
    c = g.numbers(pbr, "baseColorFactor", f"{mw}.pbrMetallicRoughness", 4, DEFAULT_BASE_COLOR)
    return (float(c[0]), float(c[1]), float(c[2]), float(c[3]))


# ---------------------------------------------------------------------------- tips


def _leaf_tips(skeleton: Skeleton, positions: NDArray[np.float32], joints: NDArray[np.uint16],
               weights: NDArray[np.float32]) -> NDArray[np.float64]:
    """Tips of leaf joints (head, toes, finger ends): the far end of the bone's flesh.

    The flesh is the vertices the joint dominates (weight > 0.5); the far end is the centre
    of the cap of flesh that reaches farthest along the bone's incoming direction (the
    parent-to-joint offset), within 10% of the farthest reach. So the head's tip is the
    crown, a toe's the toe tip, a finger's the fingertip. A centroid would not do: the face
    is densely tessellated and would tilt the head's tip forward. A leaf that dominates no
    vertex continues its parent bone by half its offset. Other joints keep zero tips.
    """
    rest = skeleton.rest_positions()
    rows = np.arange(len(weights))
    best = np.argmax(weights, axis=1)
    dominant = np.where(weights[rows, best] > _TIP_WEIGHT, joints[rows, best].astype(np.int64), -1)
    tips = np.zeros((skeleton.num_joints, 3))
    for j in range(1, skeleton.num_joints):  # a lone root has no direction: tip stays zero
        if skeleton.children(j):
            continue
        tips[j] = 0.5 * skeleton.offsets[j]
        length = float(np.linalg.norm(skeleton.offsets[j]))
        flesh = positions[dominant == j].astype(np.float64) - rest[j]
        if len(flesh) and length > 0.0:
            reach = flesh @ (skeleton.offsets[j] / length)
            if reach.max() > 0.0:
                tips[j] = flesh[reach >= _TIP_CAP * reach.max()].mean(axis=0)
    return tips


# ---------------------------------------------------------------------------- public


def _frozen(array: NDArray[Any]) -> NDArray[Any]:
    array.setflags(write=False)
    return array


def read_gltf(path: str | Path) -> SkinnedMesh:
    """Read the first skinned mesh of a .glb file.

    Skeleton order: the skin's ``joints`` order, except that a joint listed before its
    parent joint is moved after it (a stable topological sort), so ``parents[j] < j`` and the
    root comes first; when the skin is already parents-first (as in the MakeHuman asset) the
    order is exactly the skin's. Nodes above the root joint that are not joints are left out,
    but the root's offset is its world position, so ``rest_positions()`` are the joints'
    bind positions. ``joints`` and ``inverse_bind`` are remapped to this order.
    """
    name = str(path)
    try:
        data = Path(path).read_bytes()
    except OSError as err:
        raise FormatError(name, None, f"cannot read the file: {err.strerror}") from None
    g = _split_glb(name, data)
    mesh_index, skin_index = _skinned_node(g)
    skeleton, order, inverse_bind = _skin_skeleton(g, skin_index)
    prims = _read_mesh(g, mesh_index, len(order))
    bases = np.cumsum([0] + [len(p.positions) for p in prims])
    positions = np.concatenate([p.positions for p in prims])
    # Skin index -> skeleton index, so joints index the Skeleton directly.
    to_skeleton = np.empty(len(order), np.uint16)
    to_skeleton[order] = np.arange(len(order), dtype=np.uint16)
    joints = to_skeleton[np.concatenate([p.joints for p in prims])]
    weights = np.concatenate([p.weights for p in prims])
    skeleton = skeleton.with_offsets(skeleton.offsets,
                                     _leaf_tips(skeleton, positions, joints, weights))
    uv_list = [p.uvs for p in prims if p.uvs is not None]
    uvs = np.concatenate(uv_list) if len(uv_list) == len(prims) else None
    return SkinnedMesh(
        skeleton=skeleton,
        positions=_frozen(positions),
        normals=_frozen(np.concatenate([p.normals for p in prims])),
        uvs=None if uvs is None else _frozen(uvs),
        indices=_frozen(np.concatenate([p.indices + np.uint32(b)
                                        for p, b in zip(prims, bases, strict=False)])),
        joints=_frozen(joints),
        weights=_frozen(weights),
        inverse_bind=_frozen(inverse_bind.astype(np.float32)),
        base_color=_base_color(g, prims[0].material),
    )


def makehuman_path() -> Path:
    """The CC0 MakeHuman game-engine rig shipped inside the package."""
    return Path(__file__).resolve().parent.parent / "assets" / MAKEHUMAN_ASSET


@functools.lru_cache(maxsize=1)
def load_makehuman() -> SkinnedMesh:
    """The shipped MakeHuman avatar, read once (its arrays are read-only; share freely)."""
    return read_gltf(makehuman_path())
