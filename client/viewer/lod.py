"""Levels of detail of the avatar mesh, and which level each avatar gets in a frame.

Why: on a software rasterizer (Mesa llvmpipe) the cost of a frame is set by its triangle
count, not its pixels: ~0.1-0.15 us per triangle in the single-threaded front end
(measured on this 2-core machine: 16 full MakeHuman meshes, 428k triangles, take ~60 ms
at any resolution). So the frame's triangles are budgeted:

- ``build_lods`` makes coarser meshes by vertex clustering: the bind-pose vertices snap
  to a grid of ``cell`` metres, one vertex per occupied cell is kept (the one nearest the
  cell's centroid) and the triangles are re-indexed, dropping those that collapse. Cells
  are also split by the vertex's dominant joint, so no triangle joins two body parts
  that move apart (fingers, an arm and the hip). Every level indexes the *same* vertex
  buffer: one upload, one skinning shader, any level.
- Triangles are sorted along a Morton (Z-order) curve of their centroids and vertices
  renumbered in first-use order: the draw module then shades each vertex about once
  instead of ~3 times and the front end runs ~30% faster.
- ``choose_levels`` gives every avatar the coarsest level whose cell still projects to
  at most ``cell_px`` pixels (finer would be invisible), then, while the frame is over
  its triangle budget, coarsens the avatar whose cells are currently the smallest on
  screen (where the loss shows least).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from posecast.solver.readers.gltf import SkinnedMesh

# cell sizes of the levels, metres; 0 is the full mesh. Triangles of the MakeHuman mesh:
# 26.8k, 13.0k, 9.8k, 7.3k, 5.6k, 4.3k, 2.3k
DEFAULT_CELLS = (0.0, 0.01, 0.015, 0.02, 0.025, 0.03, 0.045)
# the triangles a frame may draw on a software rasterizer: 16 avatars then fit a 16 ms
# frame with headroom (`posecast bench render`, docs/performance.md)
SOFTWARE_BUDGET = 60_000
# on a GPU triangles are cheap: enough for ~75 full-detail avatars
HARDWARE_BUDGET = 2_000_000
SOFTWARE_RENDERERS = ("llvmpipe", "softpipe", "swiftshader", "software rasterizer")


def default_budget(gl_renderer: str) -> int:
    """The triangle budget for a GL_RENDERER string (software rasterizers get a small one)."""
    name = gl_renderer.lower()
    return SOFTWARE_BUDGET if any(s in name for s in SOFTWARE_RENDERERS) else HARDWARE_BUDGET
AVATAR_HEIGHT_M = 1.75  # to turn a projected height into pixels per metre


@dataclass(frozen=True, eq=False)
class LodMesh:
    """The mesh's levels over one vertex order. ``vertex_order[i]`` is the mesh vertex
    uploaded at position i; ``levels[k]`` the triangle indices (into that upload order)
    of level k, whose cell size is ``cells[k]``."""

    vertex_order: NDArray[np.intp]
    cells: tuple[float, ...]
    levels: tuple[NDArray[np.uint32], ...]

    @property
    def triangles(self) -> list[int]:
        return [len(ix) // 3 for ix in self.levels]


def cluster(mesh: SkinnedMesh, cell: float) -> NDArray[np.int64]:
    """(T', 3) triangles of ``mesh`` clustered at ``cell`` metres (mesh vertex ids)."""
    tri = np.asarray(mesh.indices, dtype=np.int64).reshape(-1, 3)
    if cell <= 0.0:
        return tri
    p = np.asarray(mesh.positions, dtype=np.float64)
    dominant = mesh.joints[np.arange(len(p)), np.argmax(mesh.weights, axis=1)]
    cells = np.floor((p - p.min(axis=0)) / cell).astype(np.int64)
    keys = np.concatenate([cells, dominant[:, None].astype(np.int64)], axis=1)
    _, member, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    member = member.reshape(-1)
    centroid = np.zeros((len(counts), 3))
    np.add.at(centroid, member, p)
    centroid /= counts[:, None]
    dist = np.linalg.norm(p - centroid[member], axis=1)
    order = np.lexsort((dist, member))  # by cluster, nearest to its centroid first
    first = np.ones(len(order), dtype=bool)
    first[1:] = member[order[1:]] != member[order[:-1]]
    representative = np.empty(len(counts), dtype=np.int64)
    representative[member[order[first]]] = order[first]
    tri = representative[member[tri]]
    keep = (tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 0] != tri[:, 2])
    tri = tri[keep]
    # fine triangles that collapsed onto the same coarse one: keep one (same winding)
    _, unique = np.unique(np.sort(tri, axis=1), axis=0, return_index=True)
    return tri[np.sort(unique)]


def _morton_sorted(tri: NDArray[np.int64], p: NDArray[np.float64]) -> NDArray[np.int64]:
    """Triangles in Z-order of their centroids (10 bits per axis)."""
    centre = p[tri].mean(axis=1)
    lo, hi = centre.min(axis=0), centre.max(axis=0)
    q = ((centre - lo) / np.maximum(hi - lo, 1e-9) * 1023).astype(np.int64)

    def spread(x: NDArray[np.int64]) -> NDArray[np.int64]:  # 10 bits -> every third bit
        x = x & 0x3FF
        x = (x | (x << 16)) & 0x30000FF
        x = (x | (x << 8)) & 0x300F00F
        x = (x | (x << 4)) & 0x30C30C3
        return (x | (x << 2)) & 0x9249249

    code = spread(q[:, 0]) | (spread(q[:, 1]) << 1) | (spread(q[:, 2]) << 2)
    return tri[np.argsort(code, kind="stable")]


def build_lods(mesh: SkinnedMesh, cells: Sequence[float] = DEFAULT_CELLS) -> LodMesh:
    """Every level of ``cells`` (the first should be 0: the full mesh); see the docstring."""
    p = np.asarray(mesh.positions, dtype=np.float64)
    V = len(p)
    full = _morton_sorted(cluster(mesh, 0.0), p)
    flat = full.reshape(-1)
    _, first_use = np.unique(flat, return_index=True)
    used = flat[np.sort(first_use)]
    unused = np.setdiff1d(np.arange(V), used)  # vertices no triangle uses go last
    vertex_order = np.concatenate([used, unused]).astype(np.intp)
    new_id = np.empty(V, dtype=np.int64)
    new_id[vertex_order] = np.arange(V)
    levels = []
    for cell in cells:
        tri = full if cell <= 0.0 else _morton_sorted(cluster(mesh, cell), p)
        levels.append(np.ascontiguousarray(new_id[tri].reshape(-1), dtype=np.uint32))
    return LodMesh(vertex_order, tuple(float(c) for c in cells), tuple(levels))


def choose_levels(heights_px: Sequence[float], lods: LodMesh, budget: int = SOFTWARE_BUDGET,
                  cell_px: float = 1.5) -> list[int]:
    """A level per avatar from its projected height in pixels (<= 0: off screen, which
    gets the coarsest level); see the module docstring."""
    cells = np.asarray(lods.cells)
    tris = lods.triangles
    coarsest = len(cells) - 1
    px_per_m = np.maximum(np.asarray(heights_px, dtype=np.float64), 0.0) / AVATAR_HEIGHT_M
    levels = []
    for ppm in px_per_m:
        if ppm <= 0.0:
            levels.append(coarsest)
            continue
        fine_enough = np.nonzero(cells * ppm <= cell_px)[0]  # includes the full mesh (0)
        levels.append(int(fine_enough.max()))
    total = sum(tris[k] for k in levels)
    while total > budget:
        candidates = [b for b, k in enumerate(levels) if k < coarsest]
        if not candidates:
            break
        # the avatar whose next-coarser cell is smallest on screen loses least
        b = min(candidates, key=lambda i: cells[levels[i] + 1] * px_per_m[i])
        total -= tris[levels[b]] - tris[levels[b] + 1]
        levels[b] += 1
    return levels
