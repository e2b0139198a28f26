"""Inverse kinematics: solve B avatars in one call, by solver name.

    state = PoseBatch.canonical(rig, B)
    Solver(rig).solve(targets, state)   # targets: (B, 6 or more, 7), slot order of
                                        # solver.tracking.devices; weights (B, ND)

Solvers (one file each): ``analytic`` (the default: closed-form limbs and spine plus a
short refinement), ``dls`` (damped least squares over whole chains) and ``paper`` (the
paper's reduced-Jacobian pseudo-inverse). Every solver warm-starts from the pose in the
state and writes the new pose into it; every solver keeps every joint within its limits.

A batch of two or more avatars is solved on all cores (numba ``prange``, one avatar per
task: the results are bit for bit those of one avatar at a time).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numba
import numpy as np
from numpy.typing import NDArray

from posecast.solver.choices import DEFAULT_SOLVER as DEFAULT_SOLVER
from posecast.solver.choices import SOLVERS as SOLVERS
from posecast.solver.ik.analytic import solve_analytic_batch
from posecast.solver.ik.chains import ChainArrays, chain_arrays
from posecast.solver.ik.dls import solve_dls_batch
from posecast.solver.ik.paper import solve_paper_batch
from posecast.solver.rig import Rig
from posecast.solver.tracking.devices import MAIN
from posecast.solver.tracking.layout import ND

# numba's OpenMP workers spin after each parallel solve, by default for milliseconds: a
# server solving once a frame would keep a core busy for nothing, and a spinning worker
# that loses its core stalls the next solve. A few microseconds still catch back-to-back
# solves. Read when numba starts its threads; a value already set wins.
os.environ.setdefault("GOMP_SPINCOUNT", "1000")

# paper: metres (and radians) of error one iteration may act on; see solver/ik/paper.py
STEP_LIMIT = 0.005


@dataclass(frozen=True)
class SolverOptions:
    max_iterations: int | None = None  # per chain; None: the solver's own default
    epsilon: float = 1e-4  # stop when the error norm (m and weighted rad) is below this
    damping: float | None = None  # lambda; None: the solver's tuned default
    rotation_weight: float = 0.3  # metres per radian when errors are compared
    # paper only: the error each iteration may act on, clamped to this norm (m, rad); the
    # authors' released code clamps it (dMax, after Buss); None: the solver's default
    step_limit: float | None = None


DEFAULTS: dict[str, dict[str, float]] = {
    # tuned on the Vive recordings
    "analytic": {"max_iterations": 4, "damping": 0.02},
    "dls": {"max_iterations": 20, "damping": 0.05},
    "paper": {"max_iterations": 100, "damping": 1e-3, "step_limit": STEP_LIMIT},
}


@dataclass(eq=False)
class PoseBatch:
    """The pose of B avatars: local joint rotations and the root joint's position."""

    rotations: NDArray[np.float64]  # (B, J, 4)
    root: NDArray[np.float64]  # (B, 3)
    iterations: NDArray[np.int64] = field(default=None)  # type: ignore[arg-type]

    def __post_init__(self) -> None:
        if self.iterations is None:
            self.iterations = np.zeros(self.rotations.shape[0], dtype=np.int64)

    @classmethod
    def canonical(cls, rig: Rig, batch: int) -> PoseBatch:
        rot = np.ascontiguousarray(np.broadcast_to(rig.canonical, (batch, *rig.canonical.shape)))
        root = np.repeat(rig.skeleton.offsets[:1], batch, axis=0)
        return cls(rot.copy(), root.copy())


class Solver:
    """A named solver bound to one rig topology (all avatars of a batch share it; their
    bone lengths may differ)."""

    def __init__(self, rig: Rig, name: str = DEFAULT_SOLVER,
                 options: SolverOptions | None = None) -> None:
        if name not in SOLVERS:
            raise ValueError(f"unknown solver {name!r}: choose one of {', '.join(SOLVERS)}")
        self.rig = rig
        self.name = name
        self.options = options or SolverOptions()
        d = DEFAULTS[name]
        self.max_iterations = int(self.options.max_iterations
                                  if self.options.max_iterations is not None
                                  else d["max_iterations"])
        self.damping = float(self.options.damping if self.options.damping is not None
                             else d["damping"])
        self.step_limit = float(self.options.step_limit if self.options.step_limit is not None
                                else d.get("step_limit", 0.0))
        self.arrays: ChainArrays = chain_arrays(rig)

    def analytic_args(self, offsets: NDArray[np.float64], targets: NDArray[np.float64],
                      weights: NDArray[np.float64], rotations: NDArray[np.float64],
                      root: NDArray[np.float64], iterations: NDArray[np.int64]
                      ) -> tuple[object, ...]:
        """The analytic solver's arguments over arrays of avatars (offsets (B or 1, J, 3),
        targets (B, ND, 7), weights (B, ND), rotations (B, J, 4), root (B, 3), iterations
        (B,)), as ``solve_analytic_batch`` and ``solver.ik.shared`` take them."""
        if self.name != "analytic":
            raise ValueError(f"not the analytic solver: {self.name}")
        a, o = self.arrays, self.options
        return (a.parents, offsets, a.canonical, a.pre, a.post, a.lo, a.hi, a.dofmask,
                a.pelvis, a.chains, a.lengths, targets, weights, rotations, root,
                o.rotation_weight, self.damping, self.max_iterations, o.epsilon, iterations)

    def solve(self, targets: NDArray[np.float64], state: PoseBatch,
              offsets: NDArray[np.float64] | None = None,
              weights: NDArray[np.float64] | None = None) -> None:
        """Solve every avatar of the batch towards its targets, in place: (B, 6, 7), the
        body's six (rig.EFFECTORS), or (B, ND, 7) with ``weights`` (B, ND) for the
        elbow, knee and chest trackers that steer the analytic solver (the others use
        the six). ``offsets`` (B, J, 3) gives each avatar's bone lengths; default: the
        rig's."""
        a = self.arrays
        if offsets is None:
            offsets = self.rig.skeleton.offsets[None]
        targets, weights = _slots(targets, weights)
        o = self.options
        serial = numba.get_num_threads() == 1  # see PARALLEL_MIN_AVATARS
        if self.name == "analytic":
            args = self.analytic_args(offsets, targets, weights, state.rotations,
                                      state.root, state.iterations)
            # (mypy reads the compiled dispatcher's call as fixed-arity)
            solve_analytic_batch(*args, serial)  # type: ignore[call-arg]
        elif self.name == "dls":
            solve_dls_batch(a.parents, offsets, a.pre, a.post, a.lo, a.hi, a.dofmask,
                            a.pelvis, a.chains, a.lengths, targets, state.rotations,
                            state.root, o.rotation_weight, self.damping,
                            self.max_iterations, o.epsilon, state.iterations, serial)
        else:
            solve_paper_batch(a.parents, offsets, a.pre, a.post, a.lo, a.hi, a.dofmask,
                              a.pelvis, a.paper_chains, a.paper_lengths, targets,
                              state.rotations, state.root, self.damping,
                              self.max_iterations, o.epsilon, self.step_limit,
                              state.iterations, serial)


def _slots(targets: NDArray[np.float64], weights: NDArray[np.float64] | None
           ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Targets and weights in every slot: six targets alone steer nothing."""
    if targets.shape[1] == ND and weights is not None:
        return targets, weights
    full = np.zeros((targets.shape[0], ND, 7))
    full[:, :, 6] = 1.0
    full[:, :MAIN] = targets[:, :MAIN]
    out = np.zeros((targets.shape[0], ND))
    out[:, :MAIN] = 1.0
    if weights is not None:
        out[:, MAIN:targets.shape[1]] = weights[:, MAIN:targets.shape[1]]
        full[:, MAIN:targets.shape[1]] = targets[:, MAIN:]
    return full, out
