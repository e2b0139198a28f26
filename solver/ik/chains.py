"""Kinematic chains of a rig, as the compiled solvers take them.

Five chains, one per effector besides the pelvis (which the hip tracker drives directly),
solved in this order because each later chain hangs from an earlier one:
head (spine..head), hand_l, hand_r (clavicle..hand), foot_l, foot_r (thigh..foot).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from posecast.solver.rig import Rig

CHAIN_EFFECTORS = ("head", "hand_l", "hand_r", "foot_l", "foot_r")
MAX_CHAIN = 8


@dataclass(frozen=True, eq=False)
class ChainArrays:
    """Everything a compiled solver needs about a rig, as plain arrays."""

    parents: NDArray[np.int64]  # (J,)
    canonical: NDArray[np.float64]  # (J, 4)
    pre: NDArray[np.float64]  # (J, 4)
    post: NDArray[np.float64]  # (J, 4)
    lo: NDArray[np.float64]  # (J, 3)
    hi: NDArray[np.float64]  # (J, 3)
    dofmask: NDArray[np.bool_]  # (J, 3) which limit axes turn
    pelvis: int
    chains: NDArray[np.int64]  # (5, MAX_CHAIN) joints, parents first, effector last, -1 pad
    lengths: NDArray[np.int64]  # (5,)
    # the paper's reduced chains: the three joints before each effector (two for the
    # feet, whose third predecessor, the pelvis, is driven by the hip tracker)
    paper_chains: NDArray[np.int64]  # (5, 4): predecessors then the effector, -1 pad
    paper_lengths: NDArray[np.int64]  # (5,) including the effector


def chain_arrays(rig: Rig) -> ChainArrays:
    r = rig.roles
    chains = np.full((5, MAX_CHAIN), -1, dtype=np.int64)
    lengths = np.zeros(5, dtype=np.int64)
    paper = np.full((5, 4), -1, dtype=np.int64)
    paper_len = np.zeros(5, dtype=np.int64)
    spine = sorted(r["spine"] + r["chest"] + r.get("neck", []) + r["head"])
    limbs = {"hand": ("clavicle", "upperarm", "forearm", "hand"),
             "foot": ("thigh", "shin", "foot")}
    for c, name in enumerate(CHAIN_EFFECTORS):
        if name == "head":
            joints = spine
        else:
            base, side = name.split("_")
            joints = [r[f"{role}_{side}"][0] for role in limbs[base]]
        _check_contiguous(rig, joints, name)
        chains[c, : len(joints)] = joints
        lengths[c] = len(joints)
        pred = joints[-4:]  # a foot chain has only thigh, shin, foot
        paper[c, : len(pred)] = pred
        paper_len[c] = len(pred)
    dofmask = (rig.hi - rig.lo) > 0.0
    return ChainArrays(
        parents=rig.skeleton.parents.astype(np.int64),
        canonical=rig.canonical, pre=rig.pre, post=rig.post, lo=rig.lo, hi=rig.hi,
        dofmask=dofmask, pelvis=rig.role("pelvis"), chains=chains, lengths=lengths,
        paper_chains=paper, paper_lengths=paper_len)


def _check_contiguous(rig: Rig, joints: list[int], name: str) -> None:
    parents = rig.skeleton.parents
    for a, b in itertools.pairwise(joints):
        if parents[b] != a:
            raise ValueError(f"chain {name}: {rig.skeleton.names[b]} does not hang from "
                             f"{rig.skeleton.names[a]}")


def driven_joints(rig: Rig) -> NDArray[np.int64]:
    """The joints a solve may turn, ascending: the pelvis and every chain's. The others
    keep the rotations they were calibrated with (a roster sends them once)."""
    arrays = chain_arrays(rig)
    chained = arrays.chains[arrays.chains >= 0]
    return np.unique(np.concatenate([chained, [arrays.pelvis]])).astype(np.int64)
