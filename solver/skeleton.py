"""A joint hierarchy: names, parents and rest offsets.

The rest pose of every skeleton is the pose with identity local rotations (true of BVH
files and of the MakeHuman glTF rig, whose bind rotations are identity). Joints are
stored parents-first (``parents[j] < j``), so one forward pass computes every global
transform. Degrees of freedom and angle limits are not stored here: they are data in
``solver/limits.py``, mapped onto a skeleton by the name tables of ``solver/naming.py``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray


class SkeletonError(ValueError):
    """A joint hierarchy that cannot be used (bad parents, unknown joint, ...)."""


@dataclass(frozen=True, eq=False)
class Skeleton:
    names: tuple[str, ...]
    parents: NDArray[np.int32]  # (J,) parent index, -1 for the root
    offsets: NDArray[np.float64]  # (J, 3) rest translation from the parent, metres
    # (J, 3) offset of a leaf joint's end point (BVH "End Site", the tip of a bone with no
    # child joint), zero where unknown; gives leaf bones (head, toes) a direction.
    tips: NDArray[np.float64] = field(default=None)  # type: ignore[arg-type]
    # joint name -> canonical role, given by the user (``eval --map``) for joints whose
    # names no table knows; naming.roles honours it before names and shape
    role_names: Mapping[str, str] | None = None

    def __post_init__(self) -> None:
        parents = np.asarray(self.parents, dtype=np.int32)
        offsets = np.asarray(self.offsets, dtype=np.float64)
        n = len(self.names)
        tips = np.zeros((n, 3)) if self.tips is None else np.asarray(self.tips, np.float64)
        if parents.shape != (n,) or offsets.shape != (n, 3) or tips.shape != (n, 3):
            raise SkeletonError(
                f"skeleton arrays disagree: {n} names, parents {parents.shape}, "
                f"offsets {offsets.shape}, tips {tips.shape}")
        if n == 0 or parents[0] != -1:
            raise SkeletonError("the first joint must be the root (parent -1)")
        for j in range(1, n):
            if not 0 <= parents[j] < j:
                raise SkeletonError(
                    f"joint {self.names[j]!r}: parent index {parents[j]} must come before it")
        if len(set(self.names)) != n:
            raise SkeletonError("joint names must be unique")
        if not (np.all(np.isfinite(offsets)) and np.all(np.isfinite(tips))):
            raise SkeletonError("joint offsets must be finite numbers")
        object.__setattr__(self, "parents", parents)
        object.__setattr__(self, "offsets", offsets)
        object.__setattr__(self, "tips", tips)

    @property
    def num_joints(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise SkeletonError(f"no joint named {name!r} in this skeleton") from None

    def children(self, j: int) -> list[int]:
        return [int(c) for c in np.nonzero(self.parents == j)[0]]

    def rest_positions(self) -> NDArray[np.float64]:
        """Global joint positions in the rest pose (identity rotations), (J, 3)."""
        pos = np.zeros((self.num_joints, 3))
        for j in range(1, self.num_joints):
            pos[j] = pos[self.parents[j]] + self.offsets[j]
        pos += self.offsets[0]
        return pos

    def with_offsets(self, offsets: NDArray[np.float64],
                     tips: NDArray[np.float64] | None = None) -> Skeleton:
        """The same hierarchy with other bone offsets (a calibrated person)."""
        return Skeleton(self.names, self.parents, offsets,
                        self.tips if tips is None else tips, self.role_names)
