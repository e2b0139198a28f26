"""Write one avatar's motion as a BVH file that Blender, three.js and posecast read.

The skeleton (names, parents, rest offsets: an ``AvatarInfo`` as a ``Skeleton``) becomes
the HIERARCHY and its poses, resampled to a fixed rate (``solver.resample``), the MOTION.
What the file is, and why:

- Units: centimetres (``units_per_metre`` 100), the unit of most BVH exports
  (MotionBuilder, Mixamo); ``readers.bvh.infer_scale`` reads an adult in them as such.
  Blender imports at 1 unit = 1 m, so its Scale option is 0.01 for these files.
- Channels: the root has six, ``Xposition Yposition Zposition Zrotation Xrotation
  Yrotation``; every other joint three rotations in the same order (all three always:
  Blender's importer reads a joint's x, y and z rotation whenever it has one). Joints
  keep their rest offsets: posecast's bones do not change length within a take.
- The root's OFFSET is 0 0 0 and its position channels hold its position: Blender and
  posecast read position channels as the position, three.js adds them to the OFFSET, and
  a zero OFFSET makes all three agree.
- Rotations: posecast's local rotations are BVH's (a child's global rotation is its
  parent's times its local one, its position the parent's plus the parent's rotation of
  its offset), as Euler angles in degrees whose curves stay continuous (``solver.euler``).
- Joints in depth-first order (the order BVH's nesting forces), each leaf with an End
  Site: the skeleton's tip where known, else half its bone again along the bone
  (``_tip``), so that Blender gives the leaf bone a length and a direction.
- Names: whitespace and braces, which would break a BVH line, and the characters
  three.js reserves in the names its animation tracks bind by (``[ ] . : /``) become
  "_"; a name made equal to another gets a suffix (``bvh_names``).
- Layout: one keyword per line, "{" and "}" on their own lines, as Blender's line-based
  parser expects; numbers with 6 decimals (1e-8 m, 1e-6 deg).

Why not a library: the BVH packages on PyPI either only read (``bvh``), pin exact
versions of their own dependencies and take minutes over thousands of frames
(``bvhio``), or pull plotting and GUI stacks into a server install (``pybvh`` needs
matplotlib, ``bvhtools`` raylib, matplotlib and scipy), and none makes continuous Euler
curves from quaternions or resamples irregular instants, the two parts that take care;
the text itself is a few dozen lines.
"""

from __future__ import annotations

import io
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from posecast.solver.euler import euler_zxy
from posecast.solver.resample import resample
from posecast.solver.skeleton import Skeleton

Array = NDArray[np.float64]

CENTIMETRES = 100.0  # file units per metre: the default
ROOT_CHANNELS = "CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation"
JOINT_CHANNELS = "CHANNELS 3 Zrotation Xrotation Yrotation"
DECIMALS = 6
TIP_SHARE = 0.5  # a leaf without a known tip: its bone continued by this share of it
MIN_TIP_M = 0.01  # ... and at least this long, so that no importer sees a zero bone
_UNSAFE = re.compile(r"[\s{}\[\].:/]+")


@dataclass(frozen=True)
class BvhExport:
    """What was written: the path, the frames at ``fps``, and each joint's name in the
    file (``names[j]`` for skeleton joint j; differs where sanitised)."""

    path: Path
    frames: int
    fps: float
    names: tuple[str, ...]


def export_bvh(path: str | Path, skeleton: Skeleton, times: Array, roots: Array,
               rotations: Array, fps: float | None = None,
               units_per_metre: float = CENTIMETRES) -> BvhExport:
    """Write the motion (``times`` (F,) seconds, ``roots`` (F, 3) metres, ``rotations``
    (F, J, 4) local quaternions x y z w) to ``path`` as BVH at ``fps`` (None: the
    recording's own rate, ``resample.default_fps``). ValueError names what is wrong."""
    text, frames, rate, names = bvh_text(skeleton, times, roots, rotations, fps,
                                         units_per_metre)
    path = Path(path)
    path.write_text(text, encoding="utf-8")
    return BvhExport(path, frames, rate, names)


def bvh_text(skeleton: Skeleton, times: Array, roots: Array, rotations: Array,
             fps: float | None = None, units_per_metre: float = CENTIMETRES
             ) -> tuple[str, int, float, tuple[str, ...]]:
    """The BVH file as text, with its frame count, rate and joint names (as written)."""
    if not (np.isfinite(units_per_metre) and units_per_metre > 0.0):
        raise ValueError(f"units_per_metre must be a positive number, got {units_per_metre}")
    rotations = np.asarray(rotations, dtype=np.float64)
    if rotations.ndim == 3 and rotations.shape[1] != skeleton.num_joints:
        raise ValueError(f"rotations have {rotations.shape[1]} joints, the skeleton "
                         f"{skeleton.num_joints}")
    motion = resample(times, roots, rotations, fps)
    names = bvh_names(skeleton.names)
    order = depth_first(skeleton)
    out = io.StringIO()
    out.write("HIERARCHY\n")
    _write_joint(out, skeleton, names, 0, 0, units_per_metre)
    frames = motion.times.size
    # the shortest text that reads back as the same float: 1 / it is the rate exactly,
    # which Blender's "update scene FPS" turns into its frame rate
    out.write(f"MOTION\nFrames: {frames}\nFrame Time: {1.0 / motion.fps!r}\n")
    angles = np.degrees(euler_zxy(motion.rotations[:, order]))  # (F, J, 3)
    values = np.concatenate([motion.roots * units_per_metre,
                             angles.reshape(frames, -1)], axis=1)
    row = " ".join([f"%.{DECIMALS}f"] * values.shape[1])
    out.write("\n".join(row % tuple(r) for r in values.tolist()))
    out.write("\n")
    return out.getvalue(), frames, motion.fps, names


def bvh_names(names: tuple[str, ...]) -> tuple[str, ...]:
    """Joint names a BVH line, and three.js' track binding, can hold: each run of
    whitespace, braces or ``[ ] . : /`` becomes "_"; never empty; all distinct (a clash
    gets "_2", "_3", ...)."""
    out: list[str] = []
    taken: set[str] = set()
    for j, name in enumerate(names):
        base = _UNSAFE.sub("_", name) or f"joint_{j}"
        candidate, k = base, 2
        while candidate in taken:
            candidate, k = f"{base}_{k}", k + 1
        taken.add(candidate)
        out.append(candidate)
    return tuple(out)


def depth_first(skeleton: Skeleton) -> NDArray[np.intp]:
    """Joint indices in the order a BVH file lists them (children in index order)."""
    order: list[int] = []
    stack = [0]
    while stack:
        j = stack.pop()
        order.append(j)
        stack.extend(reversed(skeleton.children(j)))
    return np.array(order, dtype=np.intp)


def _write_joint(out: io.StringIO, skeleton: Skeleton, names: tuple[str, ...], j: int,
                 depth: int, scale: float) -> None:
    pad = "\t" * depth
    offset = np.zeros(3) if j == 0 else skeleton.offsets[j] * scale
    out.write(f"{pad}{'ROOT' if j == 0 else 'JOINT'} {names[j]}\n{pad}{{\n")
    out.write(f"{pad}\t{_offset(offset)}\n")
    out.write(f"{pad}\t{ROOT_CHANNELS if j == 0 else JOINT_CHANNELS}\n")
    children = skeleton.children(j)
    for child in children:
        _write_joint(out, skeleton, names, child, depth + 1, scale)
    if not children:
        out.write(f"{pad}\tEnd Site\n{pad}\t{{\n{pad}\t\t{_offset(_tip(skeleton, j) * scale)}"
                  f"\n{pad}\t}}\n")
    out.write(f"{pad}}}\n")


def _offset(v: Array) -> str:
    return "OFFSET " + " ".join(f"{x:.{DECIMALS}f}" for x in v)


def _tip(skeleton: Skeleton, j: int) -> Array:
    """A leaf's End Site offset (metres): its known tip, else its bone continued (the
    nearest bone above it that has a length), else straight up."""
    if np.linalg.norm(skeleton.tips[j]) > 1e-9:
        return np.asarray(skeleton.tips[j], dtype=np.float64)
    k = j
    while k > 0:
        bone = skeleton.offsets[k]
        length = float(np.linalg.norm(bone))
        if length > 1e-9:
            return bone / length * max(TIP_SHARE * length, MIN_TIP_M)
        k = int(skeleton.parents[k])
    return np.array([0.0, MIN_TIP_M, 0.0])
