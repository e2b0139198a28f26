"""Canonical roles from a skeleton's shape alone, for rigs whose joint names say nothing.

A human skeleton, whatever its names, is a tree with two branch points that matter: the
pelvis, where the spine and both legs leave, and the chest, where the neck and both arms
leave. Fingers and toes branch too, but they are short: a branch counts only if it reaches
far (``BRANCH_SHARE`` of the body's span). Along a leg the two longest consecutive bones
are the thigh and shin (femur, tibia); the longest bone of an arm is the upper arm
(humerus). That places every limb role. The side of each limb follows from the rest pose
(left = up x forward, forward from the feet): a rest pose that does not stand (Bandai's
lies in a line) cannot tell left from right, and such a rig needs names or ``--map``.
Pure: rest offsets in, roles out.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from posecast.solver.skeleton import Skeleton, SkeletonError

Array = NDArray[np.float64]

# a child branch counts (a limb, the spine, the neck) when it reaches at least this share
# of the body's rest span (~1.7 m): fingers (~0.2 m from the wrist) and toes stay below
# it, the neck and head (~0.4 m from a mid-thorax chest) above
BRANCH_SHARE = 0.15
# a BVH rest pose faces +z (CMU, MakeHuman): the forward axis when the feet do not say
DEFAULT_FORWARD = np.array([0.0, 0.0, 1.0])


class _Shape:
    """Rest positions, bone lengths and reaches of one skeleton."""

    def __init__(self, skeleton: Skeleton) -> None:
        self.sk = skeleton
        self.pos = skeleton.rest_positions()
        self.kids = [skeleton.children(j) for j in range(skeleton.num_joints)]
        bone = np.linalg.norm(skeleton.offsets, axis=1)
        bone[0] = 0.0
        self.bone = bone
        reach = np.linalg.norm(skeleton.tips, axis=1)
        for j in range(skeleton.num_joints - 1, 0, -1):  # children come after parents
            p = skeleton.parents[j]
            reach[p] = max(reach[p], bone[j] + reach[j])
        self.reach = reach
        # the span is the longest path along the bones (fingertip to fingertip), the
        # same in any rest pose (Bandai's lies in a line); a static root's bone (from the
        # floor to the hips) is not the body's
        span = 0.0
        for j in range(skeleton.num_joints):
            if j == 0 and len(self.kids[0]) == 1:
                continue
            legs = sorted([bone[c] + reach[c] for c in self.kids[j]]
                          + [float(np.linalg.norm(skeleton.tips[j]))])
            span = max(span, sum(legs[-2:]))
        self.far = BRANCH_SHARE * span

    def branches(self, j: int) -> list[int]:
        """Children of j that start a long branch, farthest-reaching first."""
        out = [c for c in self.kids[j] if self.bone[c] + self.reach[c] >= self.far]
        return sorted(out, key=lambda c: -(self.bone[c] + self.reach[c]))

    def chain(self, start: int) -> list[int]:
        """From start, always on to the farthest-reaching child, to a leaf."""
        out = [start]
        while self.kids[out[-1]]:
            out.append(max(self.kids[out[-1]], key=lambda c: self.bone[c] + self.reach[c]))
        return out

    def segment(self, chain: list[int], k: int) -> float:
        """Length of the bone leaving chain[k]: to the next joint, or to its tip."""
        if k + 1 < len(chain):
            return float(np.linalg.norm(self.pos[chain[k + 1]] - self.pos[chain[k]]))
        return float(np.linalg.norm(self.sk.tips[chain[k]]))

    def size(self, j: int) -> int:
        """Number of joints in j's subtree."""
        return 1 + sum(self.size(c) for c in self.kids[j])


def _long_pair(shape: _Shape, chain: list[int], first: int) -> int:
    """Index k >= first in chain where bones k and k+1 together are longest."""
    ks = range(first, len(chain) - 2)
    if not ks:
        raise SkeletonError(f"the limb from {shape.sk.names[chain[0]]!r} is too short "
                            f"({len(chain)} joints) to hold its roles")
    return max(ks, key=lambda k: shape.segment(chain, k) + shape.segment(chain, k + 1))


def infer_roles(skeleton: Skeleton) -> dict[str, list[int]]:
    """Role -> joint indices from the tree and rest offsets; SkeletonError if the shape
    is not a human body with a spine, two arms from one chest and two legs."""
    shape = _Shape(skeleton)
    names = skeleton.names
    pelvis = next((j for j in range(skeleton.num_joints) if len(shape.branches(j)) >= 3),
                  None)
    if pelvis is None:
        raise SkeletonError("no joint where a spine and two legs branch off")
    # the spine branch holds arms and head: the most joints; the legs are the next two
    pelvic = sorted(shape.branches(pelvis), key=lambda c: -shape.size(c))
    spine_start, legs = pelvic[0], pelvic[1:3]
    chest = spine_start
    while len(shape.branches(chest)) < 2:  # up the spine to where both arms leave
        onward = shape.branches(chest)
        if not onward:
            raise SkeletonError(f"no joint above {names[pelvis]!r} where two arms "
                                f"branch off")
        chest = max(onward, key=lambda c: shape.size(c))
    # the two arms reach farthest (hands past the head); the neck is the longest other
    # child, however short (a head without an End Site)
    arms = shape.branches(chest)[:2]
    others = [c for c in shape.kids[chest] if c not in arms]
    if not others:
        raise SkeletonError(f"no neck or head above {names[chest]!r}, where the arms "
                            f"branch off")
    neck_start = max(others, key=lambda c: shape.bone[c] + shape.reach[c])
    out: dict[str, list[int]] = {"pelvis": [pelvis], "chest": [chest]}
    spine: list[int] = []
    j = int(skeleton.parents[chest])
    while j != pelvis:
        spine.insert(0, j)
        j = int(skeleton.parents[j])
    if spine:
        out["spine"] = spine
    head_chain = shape.chain(neck_start)
    # the head ends the chain (a head-top or eye joint would take its place: such rigs
    # are named, or mapped with --map)
    out["head"] = head_chain[-1:]
    if len(head_chain) > 1:
        out["neck"] = head_chain[:-1]
    limbs: dict[str, list[int]] = {}
    for n, start in enumerate(arms):
        c = shape.chain(start)
        # the humerus is the arm's longest bone (a clavicle measured from the spine's
        # middle, as CMU's, is nearly as long as the forearm: no pair rule here)
        if len(c) < 3:
            raise SkeletonError(f"the arm from {names[start]!r} is too short "
                                f"({len(c)} joints) to hold its roles")
        u = max(range(len(c) - 2), key=lambda k: shape.segment(c, k))
        if u == 0:  # the solvers' arm chains start one bone before the upper arm
            raise SkeletonError(f"the arm from {names[start]!r} has no clavicle before "
                                f"its upper arm")
        limbs[f"arm{n}"] = c[u - 1:u + 3]
    for n, start in enumerate(legs):
        c = shape.chain(start)
        t = _long_pair(shape, c, 0)
        limbs[f"leg{n}"] = c[t:t + 4]
    _sided(shape, out, limbs, pelvis, chest)
    return out


def _sided(shape: _Shape, out: dict[str, list[int]], limbs: dict[str, list[int]],
           pelvis: int, chest: int) -> None:
    """Name each limb's roles with its side: left = up x forward in the rest pose."""
    pos = shape.pos
    up = pos[chest] - pos[pelvis]
    up = up / max(float(np.linalg.norm(up)), 1e-9)
    forward = np.zeros(3)
    for leg in ("leg0", "leg1"):  # the feet point forward
        chain = limbs[leg]
        foot = chain[2]
        end = pos[chain[3]] if len(chain) > 3 else pos[foot] + shape.sk.tips[foot]
        forward += end - pos[foot]
    forward -= np.dot(forward, up) * up
    if np.linalg.norm(forward) < 1e-6:
        forward = DEFAULT_FORWARD - np.dot(DEFAULT_FORWARD, up) * up
    left = np.cross(up, forward)
    kinds = {"arm": ("clavicle", "upperarm", "forearm", "hand"),
             "leg": ("thigh", "shin", "foot", "toes")}
    for kind, labels in kinds.items():
        a, b = limbs[f"{kind}0"], limbs[f"{kind}1"]
        # the limbs' root joints may both sit on the midline: compare their second joints
        if np.dot(pos[a[1]] - pos[b[1]], left) < 0:
            a, b = b, a
        for chain, side in ((a, "l"), (b, "r")):
            for label, j in zip(labels, chain, strict=False):
                out[f"{label}_{side}"] = [j]
