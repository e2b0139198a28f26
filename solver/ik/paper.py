"""The paper's solver as published (section 3.1.3): per end effector its three
predecessor joints, the 6x3 Jacobian of eq. 7/8, the left pseudo-inverse of eq. 9, the
update of eqs. 10-11, the clamping of eq. 12, iterated until the error norm is below
epsilon or the iteration limit is reached, warm-started from the previous frame.

Choices where the paper is silent, following its authors' released code:
- one 6x3 Jacobian per local rotation axis: in each iteration the x, y and z axes are
  solved in turn, each with a column per predecessor joint; a joint that does not turn
  about that axis contributes a zero column;
- a small damping term lambda^2 I inside eq. 9 keeps (J^T J) invertible when a column
  vanishes;
- the error is [position difference; rotation vector to the target orientation];
- the effector bone itself takes the tracker's orientation (within its limits) after
  each iteration, since the paper's chains move only its predecessors;
- each iteration acts on the error clamped to a norm of ``step_limit`` (the authors'
  code clamps it as dMax, after Buss and Kim). Its value is not published; 5 mm
  reproduces the shape and scale of the paper's Table 2 (lag 185 ms at 5 iterations
  down to 7 ms at 100) on the authors' recordings (docs/performance.md);
- limits are clamped on the swing/twist angles of ``solver/rig.py``.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from posecast.solver.kernels import (
    PARALLEL_MIN_AVATARS,
    clamp_joint_at,
    effector_error,
    fk_joints,
    jacobian_column,
    place_root,
    set_effector_rotation,
    solve_spd,
    step_joint_at,
)


@njit(cache=True)
def paper_chain(parents, offsets, q, gq, gp, pre, post, lo, hi, dofmask,
                chain, n, target, lam, max_iter, eps, dmax):
    eff = chain[n - 1]
    e = np.empty(6)
    Jm = np.empty((6, 3))
    A = np.empty((3, 3))
    g = np.empty(3)
    dth = np.empty(3)
    npred = n - 1
    it = 0
    while it < max_iter:
        fk_joints(parents, offsets, q, gq, gp, chain, n)
        if effector_error(gq, gp, eff, target, 1.0, e) < eps:
            break
        for ax in range(3):
            fk_joints(parents, offsets, q, gq, gp, chain, n)
            norm = effector_error(gq, gp, eff, target, 1.0, e)
            if dmax > 0.0 and norm > dmax:  # the authors' per-iteration clamp (dMax)
                for r in range(6):
                    e[r] *= dmax / norm
            for i in range(npred):
                j = chain[i]
                if dofmask[j, ax]:
                    jacobian_column(gq, gp, post, j, ax, eff, 1.0, Jm, i)
                else:
                    for r in range(6):
                        Jm[r, i] = 0.0
            # eq. 9 with damping: (J^T J + lam^2 I)^-1 J^T e
            for a in range(npred):
                s = 0.0
                for r in range(6):
                    s += Jm[r, a] * e[r]
                g[a] = s
                for b in range(npred):
                    s = 0.0
                    for r in range(6):
                        s += Jm[r, a] * Jm[r, b]
                    A[a, b] = s + (lam * lam if a == b else 0.0)
            if not solve_spd(A, g, npred, dth):
                continue
            for i in range(npred):  # eqs. 10-12
                j = chain[i]
                if dofmask[j, ax]:
                    d0 = dth[i] if ax == 0 else 0.0
                    d1 = dth[i] if ax == 1 else 0.0
                    d2 = dth[i] if ax == 2 else 0.0
                    step_joint_at(q, j, pre, post, d0, d1, d2)
                    clamp_joint_at(q, j, pre, post, lo, hi)
        fk_joints(parents, offsets, q, gq, gp, chain, n - 1)
        set_effector_rotation(parents, q, gq, pre, post, lo, hi, eff, target)
        it += 1
    return it


@njit(cache=True)
def solve_paper_range(parents, offsets, pre, post, lo, hi, dofmask, pelvis, chains,
                      lengths, targets, q, root, lam, max_iter, eps, dmax, iterations,
                      first, last):
    """Avatars first..last-1 of the batch, one after the other."""
    J = q.shape[1]
    shared = offsets.shape[0] == 1
    gq = np.empty((J, 4))
    gp = np.empty((J, 3))
    for b in range(first, last):
        off = offsets[0] if shared else offsets[b]
        place_root(parents, off, q[b], root[b], gq, gp, pelvis, targets[b, 1])
        total = 0
        for c in range(chains.shape[0]):
            eff_slot = 0 if c == 0 else c + 1  # targets order: head, pelvis, hands, feet
            total += paper_chain(parents, off, q[b], gq, gp, pre, post, lo, hi, dofmask,
                                 chains[c], lengths[c], targets[b, eff_slot], lam,
                                 max_iter, eps, dmax)
        iterations[b] = total


@njit(cache=True, parallel=True)
def solve_paper_batch(parents, offsets, pre, post, lo, hi, dofmask, pelvis,
                      chains, lengths, targets, q, root, lam, max_iter, eps, dmax,
                      iterations, serial):
    # avatars are independent: spread over the cores (see PARALLEL_MIN_AVATARS); the
    # bounds are int64 in both calls so that they share one compiled version
    B = q.shape[0]
    if serial or B < PARALLEL_MIN_AVATARS:
        solve_paper_range(parents, offsets, pre, post, lo, hi, dofmask, pelvis, chains,
                          lengths, targets, q, root, lam, max_iter, eps, dmax, iterations,
                          np.int64(0), B)
    else:
        for b in prange(B):
            first = np.int64(b)
            solve_paper_range(parents, offsets, pre, post, lo, hi, dofmask, pelvis, chains,
                              lengths, targets, q, root, lam, max_iter, eps, dmax, iterations,
                              first, first + 1)
