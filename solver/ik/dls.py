"""Damped least squares over every joint of each chain: the improvement the paper itself
proposes (section 4.2). dtheta = J^T (J J^T + lambda^2 I)^-1 e with J the full 6 x n
Jacobian of the chain (spine to head: 15 columns; clavicle to hand: 9; thigh to foot: 7),
rotation errors weighted against position errors, clamped to the limits after each step,
warm-started from the previous frame."""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from posecast.solver.kernels import PARALLEL_MIN_AVATARS, dls_chain, dls_scratch, place_root


@njit(cache=True)
def solve_dls_range(parents, offsets, pre, post, lo, hi, dofmask, pelvis, chains,
                    lengths, targets, q, root, w_rot, lam, max_iter, eps, iterations,
                    first, last):
    """Avatars first..last-1 of the batch, one after the other."""
    J = q.shape[1]
    shared = offsets.shape[0] == 1
    gq = np.empty((J, 4))
    gp = np.empty((J, 3))
    scratch = dls_scratch(3 * chains.shape[1])
    qsave = np.empty((J, 4))  # unused: every iteration is kept
    for b in range(first, last):
        off = offsets[0] if shared else offsets[b]
        place_root(parents, off, q[b], root[b], gq, gp, pelvis, targets[b, 1])
        total = 0
        for c in range(chains.shape[0]):
            eff_slot = 0 if c == 0 else c + 1
            total += dls_chain(parents, off, q[b], gq, gp, pre, post, lo, hi, dofmask,
                               chains[c], lengths[c], targets[b, eff_slot], w_rot, lam,
                               max_iter, eps, scratch, False, qsave)
        iterations[b] = total


@njit(cache=True, parallel=True)
def solve_dls_batch(parents, offsets, pre, post, lo, hi, dofmask, pelvis, chains,
                    lengths, targets, q, root, w_rot, lam, max_iter, eps,
                    iterations, serial):
    # avatars are independent: spread over the cores (see PARALLEL_MIN_AVATARS); the
    # bounds are int64 in both calls so that they share one compiled version
    B = q.shape[0]
    if serial or B < PARALLEL_MIN_AVATARS:
        solve_dls_range(parents, offsets, pre, post, lo, hi, dofmask, pelvis, chains,
                        lengths, targets, q, root, w_rot, lam, max_iter, eps, iterations,
                        np.int64(0), B)
    else:
        for b in prange(B):
            first = np.int64(b)
            solve_dls_range(parents, offsets, pre, post, lo, hi, dofmask, pelvis, chains,
                            lengths, targets, q, root, w_rot, lam, max_iter, eps,
                            iterations, first, first + 1)
