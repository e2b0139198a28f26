"""The browser's avatar mesh, compacted: what the page draws, in fewer bytes.

The page skins the desktop viewer's glTF mesh (three.js's GLTFLoader). Of its 1.1 MB it
needs positions, normals, joints and weights and the triangles, not the texture
coordinates (the page has no texture); joints fit a byte (53 < 256), weights a
normalised byte each (a vertex's four sum to exactly 255/255), indices 16 bits (14,517
vertices < 65,536), and normals a normalised signed byte each (KHR_mesh_quantization,
which three.js reads: 0.5 degrees at most, for per-vertex lighting). Gzipped, 1.1 MB
becomes ~320 kB.

No I/O: bytes in, bytes out (``server.web`` serves the result, gzipped).
"""

from __future__ import annotations

import json
import struct
from typing import Any

import numpy as np
from numpy.typing import NDArray

GLB_MAGIC = b"glTF"
JSON_CHUNK = 0x4E4F534A
BIN_CHUNK = 0x004E4942
FLOAT, BYTE, UNSIGNED_BYTE, UNSIGNED_SHORT, UNSIGNED_INT = 5126, 5120, 5121, 5123, 5125
QUANTIZATION = "KHR_mesh_quantization"
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
KEEP = ("POSITION", "NORMAL", "JOINTS_0", "WEIGHTS_0")  # what the page's skinning reads
_DTYPES = {FLOAT: "<f4", BYTE: "i1", UNSIGNED_BYTE: "u1", UNSIGNED_SHORT: "<u2",
           UNSIGNED_INT: "<u4"}
_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


class MeshFormatError(ValueError):
    """Not a binary glTF this module can compact."""


def read_glb(data: bytes) -> tuple[dict[str, Any], bytes]:
    """The JSON document and the binary chunk of a .glb."""
    if len(data) < 20 or data[:4] != GLB_MAGIC:
        raise MeshFormatError("not a binary glTF (no glTF magic)")
    json_length, json_type = struct.unpack_from("<II", data, 12)
    if json_type != JSON_CHUNK:
        raise MeshFormatError("the first chunk is not JSON")
    doc = json.loads(data[20:20 + json_length])
    at = 20 + json_length
    if at + 8 > len(data):
        return doc, b""
    bin_length, bin_type = struct.unpack_from("<II", data, at)
    if bin_type != BIN_CHUNK:
        raise MeshFormatError("the second chunk is not BIN")
    return doc, data[at + 8:at + 8 + bin_length]


def write_glb(doc: dict[str, Any], binary: bytes) -> bytes:
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    binary += b"\0" * (-len(binary) % 4)
    length = 12 + 8 + len(text) + 8 + len(binary)
    return (GLB_MAGIC + struct.pack("<II", 2, length) + struct.pack("<II", len(text), JSON_CHUNK)
            + text + struct.pack("<II", len(binary), BIN_CHUNK) + binary)


def accessor_array(doc: dict[str, Any], binary: bytes, index: int) -> NDArray[Any]:
    """An accessor's values (count, width), from a view of its own (strided or not)."""
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    width = _WIDTHS[acc["type"]]
    dtype = np.dtype(_DTYPES[acc["componentType"]])
    stride = view.get("byteStride", width * dtype.itemsize)
    if stride % dtype.itemsize or stride < width * dtype.itemsize:
        raise MeshFormatError(f"accessor {index}: a stride of {stride} bytes")
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    per_row = stride // dtype.itemsize
    rows = np.frombuffer(binary, dtype, acc["count"] * per_row, start)
    return rows.reshape(acc["count"], per_row)[:, :width]


def byte_weights(weights: NDArray[np.floating]) -> NDArray[np.uint8]:
    """Weights (V, 4) as bytes whose every row sums to exactly 255 (largest remainders
    round up), as core glTF wants normalised weights to sum to one."""
    w = np.asarray(weights, dtype=np.float64)
    w = w / np.maximum(w.sum(axis=1, keepdims=True), 1e-12) * 255.0
    base = np.floor(w)
    short = (255 - base.sum(axis=1)).astype(np.int64)  # 0 to 3 units to hand out
    order = np.argsort(-(w - base), axis=1, kind="stable")
    rows = np.arange(len(w))
    for k in range(4):
        base[rows, order[:, k]] += k < short
    return base.astype(np.uint8)


def compact_mesh(glb: bytes) -> bytes:
    """The skinned mesh with only what the page reads, each in its smallest core type."""
    doc, binary = read_glb(glb)
    if len(doc.get("buffers", [])) != 1 or len(doc.get("meshes", [])) != 1:
        raise MeshFormatError("expected one buffer and one mesh")
    doc = json.loads(json.dumps(doc))  # a copy to change
    prim = doc["meshes"][0]["primitives"]
    if len(prim) != 1:
        raise MeshFormatError("expected one primitive")
    attrs = prim[0]["attributes"]
    missing = [a for a in KEEP if a not in attrs]
    if missing:
        raise MeshFormatError(f"the mesh lacks {', '.join(missing)}")
    vertices = doc["accessors"][attrs["POSITION"]]["count"]
    # accessor -> its data, component type, normalised
    arrays: dict[int, tuple[NDArray[Any], int, bool]] = {}
    for index, acc in enumerate(doc["accessors"]):
        arrays[index] = (accessor_array(doc, binary, index), acc["componentType"], False)
    normals = arrays[attrs["NORMAL"]][0].astype(np.float64)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    padded = np.zeros((vertices, 4), dtype=np.int8)  # 4-byte aligned elements (glTF)
    padded[:, :3] = np.round(normals * 127.0)
    arrays[attrs["NORMAL"]] = (padded, BYTE, True)
    joints = arrays[attrs["JOINTS_0"]][0]
    if int(joints.max()) < 256:
        arrays[attrs["JOINTS_0"]] = (joints.astype(np.uint8), UNSIGNED_BYTE, False)
    arrays[attrs["WEIGHTS_0"]] = (byte_weights(arrays[attrs["WEIGHTS_0"]][0]),
                                  UNSIGNED_BYTE, True)
    indices = prim[0].get("indices")
    if indices is not None and vertices <= 65535:
        arrays[indices] = (arrays[indices][0].astype("<u2"), UNSIGNED_SHORT, False)
    used = [attrs[a] for a in KEEP] + ([indices] if indices is not None else [])
    used += [s["inverseBindMatrices"] for s in doc.get("skins", [])
             if "inverseBindMatrices" in s]
    prim[0]["attributes"] = {a: attrs[a] for a in KEEP}
    # every accessor kept, renumbered; each in a bufferView of its own, 4-byte aligned
    keep = sorted(set(used))
    new_index = {old: new for new, old in enumerate(keep)}
    views: list[dict[str, Any]] = []
    accessors: list[dict[str, Any]] = []
    chunks: list[bytes] = []
    offset = 0
    for old in keep:
        data, component, normalized = arrays[old]
        raw = np.ascontiguousarray(data).tobytes()
        acc = dict(doc["accessors"][old])
        acc.update(bufferView=len(views), componentType=component)
        acc.pop("byteOffset", None)
        if normalized:
            acc["normalized"] = True
        view: dict[str, Any] = {"buffer": 0, "byteOffset": offset, "byteLength": len(raw)}
        if old == indices:
            view["target"] = ELEMENT_ARRAY_BUFFER
        elif old in attrs.values():
            view["target"] = ARRAY_BUFFER
        if old == attrs["NORMAL"]:
            view["byteStride"] = 4
        views.append(view)
        accessors.append(acc)
        pad = -len(raw) % 4
        chunks.append(raw + b"\0" * pad)
        offset += len(raw) + pad
    prim[0]["attributes"] = {a: new_index[attrs[a]] for a in KEEP}
    if indices is not None:
        prim[0]["indices"] = new_index[indices]
    for skin in doc.get("skins", []):
        if "inverseBindMatrices" in skin:
            skin["inverseBindMatrices"] = new_index[skin["inverseBindMatrices"]]
    doc["accessors"], doc["bufferViews"] = accessors, views
    doc["buffers"] = [{"byteLength": offset}]
    for key in ("extensionsUsed", "extensionsRequired"):
        doc[key] = sorted({*doc.get(key, []), QUANTIZATION})
    return write_glb(doc, b"".join(chunks))
