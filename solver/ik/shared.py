"""One batch of the analytic solver shared by two threads: the caller and a helper
thread that spins, on another core, waiting for work.

Waking a sleeping thread costs more in this VM than half a batch saves (see
``server.app``), so the helper never sleeps: it polls a control word in a compiled loop
that has released the GIL (``analytic_helper``). The caller posts a batch (its rows of
the avatar arrays) in that word, and both threads claim avatars from it one at a time
(compare-and-swap), so the split follows whoever is free: a helper that is not running
at that moment claims nothing, and the caller solves everything, as before.

A helper can lose its core in the middle of an avatar (it runs only when that core is
otherwise idle), so it never writes the batch's arrays: it solves a copy of its avatar's
pose into its own rows (``out_q``, ``out_root``, ``out_it``) and then marks the avatar
done with a compare-and-swap. The caller copies those results in. An avatar the helper
still holds when the caller has waited TAKEOVER_SPINS is taken over (the same
compare-and-swap, so exactly one of them wins) and solved by the caller; the helper's
late result is then dropped. Each avatar is solved by ``solve_analytic_one`` from the
same inputs either way, so the results are bit for bit those of ``solve_analytic_range``.

Whoever claims an avatar first makes its targets from its staged frame, if they are not
made yet (``solver.tracking``'s fill: lost and found devices), so that the helper takes
half of that too. The helper fills into rows of its own (a copy of the avatar's tracking
state, its targets and weights), which the caller copies in with the pose.

``control`` (``new_control``): CLAIM = seq << 40 | n << 20 | next avatar to claim; SEQ,
the caller's batch count (wrapping, never 0); STOP ends the helper; READY is set once
the helper runs its loop (without the GIL); DONE = seq << 32 | avatars solved (a late
helper's count for an earlier batch is dropped). ``state[i]`` says
who solved avatar i of batch seq: seq << 2 | HELPER or seq << 2 | CALLER.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

from posecast.solver.atomics import atomic_cas, atomic_load, atomic_store, cpu_pause
from posecast.solver.ik.analytic import analytic_work, solve_analytic_one
from posecast.solver.tracking.fill import fill_targets

CLAIM, SEQ, STOP, READY, DONE = 0, 1, 2, 3, 4
FIELD = 20  # bits of n and of the next avatar in CLAIM
MAX_BATCH = (1 << FIELD) - 1
SEQ_MOD = 1 << 22  # batch numbers wrap here (CLAIM stays positive)
HELPER, CALLER = 1, 2
# how long the caller waits for the avatars the helper holds before it solves them
# itself: spins of the wait loop (~25 ns each, so ~10 us). Waiting saves at most the rest
# of one avatar; a helper that lost its core costs the whole wait, so it is short.
TAKEOVER_SPINS = 400


def new_control() -> NDArray[np.int64]:
    return np.zeros(5, dtype=np.int64)


@njit(cache=True, nogil=True, inline="always")
def _claim(control):
    """The next unclaimed avatar of the posted batch (its index in rows), or -1; and the
    batch's seq."""
    while True:
        word = atomic_load(control, CLAIM)
        seq = word >> (2 * FIELD)
        n = (word >> FIELD) & MAX_BATCH
        i = word & MAX_BATCH
        if i >= n:
            return -1, seq
        if atomic_cas(control, CLAIM, word, word + 1):
            return i, seq


@njit(cache=True, nogil=True, inline="always")
def _count_done(control, seq):
    """One more avatar of batch seq solved (nothing if that batch is over)."""
    while True:
        word = atomic_load(control, DONE)
        if word >> 32 != seq or atomic_cas(control, DONE, word, word + 1):
            return


@njit(cache=True, nogil=True)
def analytic_helper(control, rows, state, out_q, out_root, out_it, own_track, own_targets,
                    own_weights, own_filled, parents, offsets, canon, pre, post, lo, hi,
                    dofmask, pelvis, chains, lengths, targets, weights, q, root, w_rot, lam,
                    refine, eps, iterations, filled, dev, present, has, t, shape, track):
    """The helper's loop, until STOP: claim an avatar, fill (if not filled) and solve it
    into its own rows, mark it done unless the caller took it over; spin while there is
    nothing to claim. Returns the avatars whose results it handed over."""
    work = analytic_work(q.shape[1], chains, lengths)
    handed = 0
    atomic_store(control, READY, 1)
    while atomic_load(control, STOP) == 0:
        i, seq = _claim(control)
        if i < 0:
            cpu_pause()
            continue
        before = atomic_load(state, i)
        if before >> 2 == seq:  # the caller took it over while this thread was away
            continue
        b = rows[i]
        own_filled[i] = not filled[b]
        if own_filled[i]:
            own_track[i] = track[b]
            fill_targets(dev[b], present[b], has[b], t[b], shape[b], own_track[i],
                         own_targets[i], own_weights[i])
            tg, w = own_targets[i], own_weights[i]
        else:
            tg, w = targets[b], weights[b]
        out_q[i] = q[b]
        out_root[i] = root[b]
        out_it[i] = solve_analytic_one(
            parents, offsets[b], canon, pre, post, lo, hi, dofmask, pelvis, chains,
            lengths, tg, w, out_q[i], out_root[i], w_rot, lam, refine, eps, work)
        if atomic_cas(state, i, before, (seq << 2) | HELPER):
            _count_done(control, seq)
            handed += 1
    return handed


@njit(cache=True, nogil=True)
def _solve_here(i, rows, parents, offsets, canon, pre, post, lo, hi, dofmask, pelvis,
                chains, lengths, targets, weights, q, root, w_rot, lam, refine, eps,
                iterations, filled, dev, present, has, t, shape, track, work):
    """The caller fills (if not filled) and solves avatar i of the batch in place."""
    b = rows[i]
    if not filled[b]:
        fill_targets(dev[b], present[b], has[b], t[b], shape[b], track[b], targets[b],
                     weights[b])
        filled[b] = True
    iterations[b] = solve_analytic_one(
        parents, offsets[b], canon, pre, post, lo, hi, dofmask, pelvis, chains, lengths,
        targets[b], weights[b], q[b], root[b], w_rot, lam, refine, eps, work)


@njit(cache=True, nogil=True)
def solve_analytic_shared(control, rows, n, state, out_q, out_root, out_it, own_track,
                          own_targets, own_weights, own_filled, parents, offsets, canon,
                          pre, post, lo, hi, dofmask, pelvis, chains, lengths, targets,
                          weights, q, root, w_rot, lam, refine, eps, iterations, filled,
                          dev, present, has, t, shape, track):
    """Post the avatars rows[:n] (rows of the arrays the helper was given), solve them
    with the helper, return when all are solved and in place. Returns how many the
    helper solved."""
    seq = atomic_load(control, SEQ) % SEQ_MOD + 1
    atomic_store(control, SEQ, seq)
    atomic_store(control, DONE, seq << 32)
    atomic_store(control, CLAIM, (seq << (2 * FIELD)) | (n << FIELD))
    work = analytic_work(q.shape[1], chains, lengths)
    mine = (seq << 2) | CALLER
    theirs = (seq << 2) | HELPER
    while True:
        i, _ = _claim(control)
        if i < 0:
            break
        _solve_here(i, rows, parents, offsets, canon, pre, post, lo, hi, dofmask, pelvis,
                    chains, lengths, targets, weights, q, root, w_rot, lam, refine, eps,
                    iterations, filled, dev, present, has, t, shape, track, work)
        atomic_store(state, i, mine)
        _count_done(control, seq)
    # wait for the avatars the helper holds; past TAKEOVER_SPINS, take them over: after
    # that look at each, every avatar is solved, here or handed over
    spins = 0
    while atomic_load(control, DONE) != (seq << 32) | n:
        cpu_pause()
        spins += 1
        if spins >= TAKEOVER_SPINS:
            for i in range(n):
                s = atomic_load(state, i)
                if s != mine and s != theirs and atomic_cas(state, i, s, mine):
                    _solve_here(i, rows, parents, offsets, canon, pre, post, lo, hi,
                                dofmask, pelvis, chains, lengths, targets, weights, q, root,
                                w_rot, lam, refine, eps, iterations, filled, dev, present,
                                has, t, shape, track, work)
            break
    helped = 0
    for i in range(n):
        if atomic_load(state, i) == theirs:
            b = rows[i]
            q[b] = out_q[i]
            root[b] = out_root[i]
            iterations[b] = out_it[i]
            if own_filled[i]:
                track[b] = own_track[i]
                targets[b] = own_targets[i]
                weights[b] = own_weights[i]
                filled[b] = True
            helped += 1
    return helped
